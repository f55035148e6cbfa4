"""Issue 35: three one-line bugs that passed the default tier, each pinned by an independent
computation here (not by outputs of the code under test).

* Which frames make up each FVD/KVD clip: frames whose pixels encode (sequence, index, side), a
  test-only video extractor whose features are those codes, so the sidecar's rows spell out each
  clip; expected: the protocol's `clip_length` consecutive frames of one sequence, starting every
  `clip_stride` frames, in order (written out by hand below), on sequences of unequal length.
* The headline of per-frame metrics when sequences differ in length: docs/evaluate.md says the
  mean over all frames (not over sequences or scenes); checked with scikit-image PSNR/SSIM on
  images read with PIL, and each half-sampling replicate against every half-sample enumerated.
* `compare` of two results whose protocol files differ under one `id@N`: scored for real under
  two files (the sha256 differs), not by editing a field.
"""

import itertools
import json
import math

import numpy as np
import pytest
from builders.evaluation import TEST_PROTOCOL, protocol_env
from conftest import run_cli
from PIL import Image
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from skyeyes_bench.data.layout import open_dataset
from skyeyes_bench.evaluate import evaluate, read_results
from skyeyes_bench.submission import SubmissionWriter, expected_frames

SIZE = 16
HEAD = f"""
version = 1
title = "issue 35 guards"
description = "test-only"
reference = "tests"

[data]
source = "synthtown"
train = ["train-0"]
test = ["test-0"]
width = {SIZE}
height = {SIZE}
fov_deg = 90.0

[capture]
ground_height_m = 2.0
ground_pitch_deg = 0.0
ground_step_m = 2.0
yaws_deg = [0.0, 90.0]
aerial_height_m = 52.0
aerial_pitch_deg = -45.0
sequence = "test"
"""
STATS = """
[statistics]
bootstrap_resamples = {r}
interval = 0.95
seed = 0
cluster = "{cluster}"
emcee_walkers = 16
emcee_steps = 300
emcee_burn = 100
"""


def _clip_protocol(pid: str, stride: int, data_of: str | None = None) -> str:
    head = HEAD if data_of is None else HEAD.replace("fov_deg = 90.0", f'fov_deg = 90.0\ndataset_protocol = "{data_of}"')
    return (f'id = "{pid}"' + head + f"""
[metrics.fvd]
extractor = "frameid-video-16"
resize = "none"
clip_length = 16
clip_stride = {stride}
""" + STATS.format(r=20, cluster="sequence"))


def _write_dataset(root, protocol: str, lengths: dict[tuple[int, int], int], image) -> None:
    """Scenes test-0-laneNN with sequences yawQQQ of the given lengths; `image(scene, q, index)`
    gives each ground frame. Frames are written in reverse index order, so file names
    (000000.png, ...) run against the index: only the index orders a sequence."""
    from skyeyes_bench.data.writer import DatasetWriter

    intr = {"width": SIZE, "height": SIZE, "fx": SIZE / 2, "fy": SIZE / 2, "cx": SIZE / 2, "cy": SIZE / 2}
    scenes = sorted({s for s, _ in lengths})
    names = [f"test-0-lane{s:02d}" for s in scenes]
    grey = np.full((SIZE, SIZE, 3), 0.5)
    with DatasetWriter(root, name="guards", protocol=protocol) as w:
        t = w.scene("train-0-lane00", {"ground": intr, "aerial": intr})
        t.add_aerial(grey, np.eye(4))
        t.add_ground(grey, np.eye(4), sequence="yaw000", index=0)
        t.close()
        for s, name in zip(scenes, names):
            sc = w.scene(name, {"ground": intr, "aerial": intr})
            sc.add_aerial(grey, np.eye(4))
            for q in sorted(q for s2, q in lengths if s2 == s):
                for i in reversed(range(lengths[(s, q)])):
                    c2w = np.eye(4)
                    c2w[0, 3] = 2.0 * i
                    sc.add_ground(image(s, q, i), c2w, sequence=f"yaw{q * 90:03d}", index=i)
            sc.close()
        w.finish(splits={"train": ["train-0-lane00"], "test": names})


def _write_submission(ds, out, image) -> None:
    """`image(scene_name, frame)` for every expected frame."""
    with SubmissionWriter(out, dataset=ds, method="guard", method_version="1") as w:
        for scene, f in expected_frames(ds):
            w.add(scene, f, image(scene, f))
        w.finish(timings={"fit_s": 1.0, "render_s": 1.0, "per_frame_render_s": [0.01]}, peak_memory_mb=1.0)


# --------------------------------------------------------------------------- (a) FVD/KVD clips

#: Sequence lengths (scene, yaw number) -> frames: one exactly a clip, two longer by an odd amount,
#: one a frame too short for any clip.
CLIP_LENGTHS = {(0, 0): 16, (0, 1): 21, (1, 0): 37, (1, 1): 15}
SUB_BLUE, GT_BLUE = 200, 0


def _code_pixel(scene: int, q: int, index: int, blue: int) -> np.ndarray:
    """A constant frame whose 8-bit colour names it: red = 10 scene + q + 1, green = index."""
    return np.full((SIZE, SIZE, 3), [10 * scene + q + 1, index, blue], dtype=np.uint8)


def _frame_codes_extractor():
    from skyeyes_bench.metrics.extractors import RandomVideo64

    class FrameCodes(RandomVideo64):
        """Test-only: a clip's feature is the 8-bit colour of each of its 16 frames, in order."""

        id, kind, dim = "frameid-video-16", "video", 48

        def features(self, clips, device=None):
            clips = np.asarray(clips)  # [N, T, H, W, 3] in [0, 1]
            assert clips.ndim == 5 and clips.shape[1] == 16, clips.shape
            return np.rint(clips[:, :, 0, 0, :] * 255.0).reshape(len(clips), 48).astype(np.float64)

    return FrameCodes


@pytest.fixture(scope="module")
def clip_results(tmp_path_factory):
    """Results under clip_stride 5 (clips overlap) and 16 (the official protocols' setting)."""
    from skyeyes_bench.metrics import extractors

    tmp = tmp_path_factory.mktemp("clips")
    mp = pytest.MonkeyPatch()
    mp.setitem(extractors.EXTRACTORS, "frameid-video-16", _frame_codes_extractor())
    try:
        with protocol_env(tmp, _clip_protocol("clipguard", 5)) as env:
            from builders.evaluation import install_test_protocol

            install_test_protocol(tmp, env, _clip_protocol("clipofficial", 16, data_of="clipguard@1"))
            _write_dataset(tmp / "ds", "clipguard@1", CLIP_LENGTHS,
                           lambda s, q, i: _code_pixel(s, q, i, GT_BLUE))
            ds = open_dataset(tmp / "ds")

            def sub_image(scene, f):
                return _code_pixel(int(scene[-2:]), int(f.sequence[3:]) // 90, f.index, SUB_BLUE)

            _write_submission(ds, tmp / "sub", sub_image)
            out = {}
            for pid, stride in (("clipguard@1", 5), ("clipofficial@1", 16)):
                res = evaluate(tmp / "sub", data=tmp / "ds", out=tmp / f"{pid}.json", progress=False, protocol=pid)
                out[stride] = (res, read_results(tmp / f"{pid}.json", features=True)[1]["frameid-video-16"])
            yield out
    finally:
        mp.undo()
        extractors._INSTANCES.pop("frameid-video-16", None)


def _expected_clips(sequence_id: str, stride: int) -> list[list[int]]:
    """By hand: 16 consecutive indices starting at 0, stride, 2 stride, ... while they fit."""
    scene, q = int(sequence_id.split("/")[0][-2:]), int(sequence_id.split("/")[1][3:]) // 90
    n = CLIP_LENGTHS[(scene, q)]
    out, start = [], 0
    while start + 16 <= n:
        out.append(list(range(start, start + 16)))
        start += stride
    return out


@pytest.mark.parametrize("stride", [5, 16])
def test_each_clip_is_16_consecutive_frames_of_one_sequence_at_the_protocol_stride(clip_results, stride):
    res, feats = clip_results[stride]
    seq_ids = res["dataset"]["sequences"]
    assert res["metrics"]["fvd"]["status"] == "ok"
    want_rows, want_seq = {"sub": [], "gt": []}, []
    for k, sid in enumerate(seq_ids):  # rows: sequence by sequence, clips in order (docs/evaluate.md)
        scene, q = int(sid.split("/")[0][-2:]), int(sid.split("/")[1][3:]) // 90
        for clip in _expected_clips(sid, stride):
            want_seq.append(k)
            for side, blue in (("sub", SUB_BLUE), ("gt", GT_BLUE)):
                want_rows[side].append([v for i in clip for v in (10 * scene + q + 1, i, blue)])
    # 16/21/37/15 frames: stride 5 gives 1 + 2 + 5 + 0 clips, stride 16 gives 1 + 1 + 2 + 0
    assert len(want_seq) == {5: 8, 16: 4}[stride]
    np.testing.assert_array_equal(feats["seq"], want_seq)
    for side in ("sub", "gt"):
        got = feats[side].reshape(len(want_seq), 16, 3).astype(int).tolist()
        want = np.array(want_rows[side]).reshape(len(want_seq), 16, 3).tolist()
        for c, (g, w) in enumerate(zip(got, want)):
            assert g == w, (f"{side} clip {c} of sequence {seq_ids[want_seq[c]]}: frames (code, index) "
                            f"{[tuple(x[:2]) for x in g]}, expected {[tuple(x[:2]) for x in w]}")
    assert res["metrics"]["fvd"]["n"] == len(want_seq)


# --------------------------------------------------------------------------- (b) frame weighting

#: 5 scenes (clusters), 2 sequences each, lengths 2..9: every weighting gives another number.
WEIGHT_LENGTHS = {(0, 0): 2, (0, 1): 9, (1, 0): 7, (1, 1): 3, (2, 0): 5, (2, 1): 8, (3, 0): 4, (3, 1): 2,
                  (4, 0): 9, (4, 1): 6}
WEIGHT_PROTOCOL = ('id = "weightguard"' + HEAD + """
[metrics.psnr]
aggregate = "mean"

[metrics.ssim]
aggregate = "mean"
window = 11
sigma = 1.5
k1 = 0.01
k2 = 0.03
""" + STATS.format(r=200, cluster="scene"))


@pytest.fixture(scope="module")
def weighted(tmp_path_factory):
    """A submission whose error grows with its sequence's number: long and short sequences
    score very differently, so the mean over frames is far from the mean over sequences."""
    tmp = tmp_path_factory.mktemp("weights")
    rng = np.random.default_rng(3)
    with protocol_env(tmp, WEIGHT_PROTOCOL):
        gts = {key: [rng.random((SIZE, SIZE, 3)) for _ in range(n)] for key, n in WEIGHT_LENGTHS.items()}
        _write_dataset(tmp / "ds", "weightguard@1", WEIGHT_LENGTHS, lambda s, q, i: gts[(s, q)][i])
        ds = open_dataset(tmp / "ds")
        noise = {key: 0.02 + 0.06 * j for j, key in enumerate(sorted(WEIGHT_LENGTHS))}

        def sub_image(scene, f):
            key = (int(scene[-2:]), int(f.sequence[3:]) // 90)
            return np.clip(f.image() + rng.normal(0, noise[key], f.image().shape), 0, 1)

        _write_submission(ds, tmp / "sub", sub_image)
        res = evaluate(tmp / "sub", data=tmp / "ds", out=tmp / "res.json", progress=False)
        yield tmp, res


def _by_hand(tmp, res):
    """Per-frame PSNR, SSIM and MSE from the PNGs (PIL, scikit-image), with each frame's
    sequence id, in the results' frame order."""
    out = []
    for r in res["frames"]:
        pred = np.asarray(Image.open(tmp / "sub" / r["scene"] / r["file"]).convert("RGB"), np.float64) / 255
        gt = np.asarray(Image.open(tmp / "ds" / r["scene"] / r["file"]).convert("RGB"), np.float64) / 255
        out.append({"seq": res["dataset"]["sequences"][r["sequence"]], "mse": float(np.mean((pred - gt) ** 2)),
                    "psnr": peak_signal_noise_ratio(gt, pred, data_range=1.0),
                    "ssim": structural_similarity(gt, pred, win_size=11, gaussian_weights=True, sigma=1.5,
                                                  data_range=1.0, channel_axis=2, use_sample_covariance=False)})
    return out


@pytest.mark.parametrize("metric", ["psnr", "ssim"])
def test_headline_is_the_mean_over_all_frames_with_unequal_sequences(weighted, metric):
    tmp, res = weighted
    hand = _by_hand(tmp, res)
    frames = np.array([h[metric] for h in hand])
    by_seq = {s: [h[metric] for h in hand if h["seq"] == s] for s in res["dataset"]["sequences"]}
    by_scene: dict[str, list] = {}
    for s, v in by_seq.items():
        by_scene.setdefault(s.split("/")[0], []).extend(v)
    per_frame = float(frames.mean())
    per_sequence = float(np.mean([np.mean(v) for v in by_seq.values()]))
    per_scene = float(np.mean([np.mean(v) for v in by_scene.values()]))
    tol = 1e-5 * max(1.0, abs(per_frame))
    # the data tells the three weightings apart by far more than the tolerance
    assert min(abs(per_frame - per_sequence), abs(per_frame - per_scene)) > 100 * tol
    got = res["metrics"][metric]
    assert got["value"] == pytest.approx(per_frame, abs=tol), (
        f"{metric}: results say {got['value']}; mean over frames {per_frame}, over sequences {per_sequence}, "
        f"over scenes {per_scene}")
    assert got["n"] == len(frames) == sum(WEIGHT_LENGTHS.values())
    # per sequence: the mean of its frames (SSIM) or the PSNR of its mean MSE (docs/evaluate.md)
    for sid, v in by_seq.items():
        if metric == "ssim":
            want = float(np.mean(v))
        else:
            want = -10 * math.log10(np.mean([h["mse"] for h in hand if h["seq"] == sid]))
        assert res["sequences"][sid][metric] == pytest.approx(want, abs=1e-5 * max(1.0, abs(want))), sid
        assert res["sequences"][sid]["frames"] == len(v)


@pytest.mark.parametrize("metric", ["psnr", "ssim"])
def test_every_replicate_is_the_frame_mean_of_a_half_sample_of_scenes(weighted, metric):
    """Each of the R stored replicates is the mean over the frames of some 2 of the 5 scenes
    (half-sampling), every possible half-sample enumerated here; the mean of those scenes'
    per-scene means would be another number."""
    tmp, res = weighted
    hand = _by_hand(tmp, res)
    scenes = sorted({h["seq"].split("/")[0] for h in hand})
    assert res["statistics"]["cluster"] == "scene" and res["statistics"]["clusters"] == len(scenes) == 5
    half = len(scenes) // 2
    frame_means, scene_means = [], []
    for pick in itertools.combinations(scenes, half):
        vals = [[h[metric] for h in hand if h["seq"].split("/")[0] == s] for s in pick]
        frame_means.append(float(np.mean([v for vs in vals for v in vs])))
        scene_means.append(float(np.mean([np.mean(vs) for vs in vals])))
    frame_means, scene_means = np.array(frame_means), np.array(scene_means)
    reps = np.array(res["metrics"][metric]["replicates"], dtype=np.float64)
    assert len(reps) == 200
    tol = 2e-5 * np.abs(frame_means).max()  # replicates are stored to 6 significant digits
    # the two weightings differ on every half-sample by far more than the tolerance
    assert (np.abs(frame_means - scene_means) > 20 * tol).all()
    nearest = np.abs(reps[:, None] - frame_means[None, :]).min(axis=1)
    bad = np.flatnonzero(nearest > tol)
    assert not len(bad), (f"{metric}: {len(bad)} of {len(reps)} replicates are no half-sample's mean over frames, "
                          f"e.g. replicate {bad[0]} = {reps[bad[0]]}")
    assert len({round(float(v), 4) for v in reps}) > 1  # not one degenerate draw


# --------------------------------------------------------------------------- (c) protocol files


def test_compare_refuses_results_of_two_files_under_one_protocol_ref(tmp_path, monkeypatch):
    """Two results of evaltest@1 scored under different evaltest/v1.toml files (their sha256
    differ): refused in one line, saying so; and results scored under a file that has since
    changed are refused against the installed one (compare would resample with its settings)."""
    from builders.evaluation import blurred_submission, install_test_protocol, make_dataset

    install_test_protocol(tmp_path, monkeypatch)
    ds = open_dataset(make_dataset(tmp_path / "ds", scenes=3, seqs=2, frames=4))
    sub = blurred_submission(ds, tmp_path / "sub", sigma=0.7)
    evaluate(sub, data=ds.root, out=tmp_path / "a.json", progress=False)
    changed = TEST_PROTOCOL.replace("seed = 0", "seed = 1")
    assert changed != TEST_PROTOCOL
    install_test_protocol(tmp_path, monkeypatch, changed)
    sub = blurred_submission(ds, tmp_path / "sub-changed", sigma=0.7)  # it records the file's sha256 too
    evaluate(sub, data=ds.root, out=tmp_path / "b.json", progress=False)
    evaluate(sub, data=ds.root, out=tmp_path / "c.json", progress=False)
    sha_a, sha_b = (json.loads((tmp_path / f"{n}.json").read_text())["protocol"] for n in "ab")
    assert sha_a["ref"] == sha_b["ref"] == "evaltest@1" and sha_a["sha256"] != sha_b["sha256"]

    install_test_protocol(tmp_path, monkeypatch)  # the first file again
    rc, out, err = run_cli("compare", str(tmp_path / "a.json"), str(tmp_path / "b.json"), check=2)
    assert err.count("\n") == 1 and "Traceback" not in err and not out, err
    assert "protocol evaltest@1 differs between A and B" in err
    assert sha_a["sha256"][:12] in err and sha_b["sha256"][:12] in err
    # b and c agree with each other but not with the installed file
    rc, out, err = run_cli("compare", str(tmp_path / "b.json"), str(tmp_path / "c.json"), check=2)
    assert err.count("\n") == 1 and "protocol evaltest@1 changed since A and B were scored" in err, err
    # the same pair under the file both were scored with: compared
    install_test_protocol(tmp_path, monkeypatch, changed)
    run_cli("compare", str(tmp_path / "b.json"), str(tmp_path / "c.json"), "--json")
