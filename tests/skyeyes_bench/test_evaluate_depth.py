"""The depth-based metrics end to end on SynthTown's smoke data: seen / unseen regions and warp
consistency in evaluate (a protocol that scores another one's data), results, merge, compare and
the leaderboard tables."""

import json
import math
import shutil

import numpy as np
import pytest
from builders.evaluation import TEST_PROTOCOL, install_test_protocol
from conftest import run_cli

from skyeyes_bench.data.layout import open_dataset
from skyeyes_bench.evaluate import evaluate, merge, read_results
from skyeyes_bench.metricspec import SEQUENCE_METRICS
from skyeyes_bench.comparison import compare_results
from skyeyes_bench.submission import SubmissionWriter, expected_frames, write_template

# A later synthtown version that scores synthtown@1's frames (the smoke data) with the depth
# metrics, as synthtown@3 scores synthtown@2's; lpips_* need weights the test cache lacks.
DEPTH_PROTOCOL = """
id = "synthtown"
version = 9
title = "depth metrics test"
description = "test-only: synthtown@1's data with the depth-based metrics"
reference = "tests"

[data]
source = "synthtown"
train = ["train-0"]
test = ["test-0"]
width = 48
height = 48
fov_deg = 90.0
dataset_protocol = "synthtown@1"

[capture]
ground_height_m = 2.0
ground_pitch_deg = 0.0
ground_step_m = 2.0
yaws_deg = [0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0]
aerial_height_m = 52.0
aerial_pitch_deg = -45.0
sequence = "test"

[metrics.psnr]
aggregate = "mean"
""" + "".join(f"""
[metrics.{name}]
depth_tolerance = 0.01
""" + ('extractor = "lpips-alex-v0.1"\n' if name.startswith("lpips") else "") for name in SEQUENCE_METRICS) + (
    "\n" + TEST_PROTOCOL[TEST_PROTOCOL.index("[statistics]"):])


def _write(ds, out, image_of, method):
    with SubmissionWriter(out, dataset=ds, method=method, method_version="1") as w:
        for scene, f in expected_frames(ds):
            w.add(scene, f, image_of(f))
        w.finish(timings={"fit_s": 1.0, "render_s": 1.0, "per_frame_render_s": [0.0]}, peak_memory_mb=1.0)
    return out


@pytest.fixture(scope="module")
def depth_scored(tmp_path_factory, synthtown_smoke):
    mp = pytest.MonkeyPatch()
    tmp = tmp_path_factory.mktemp("depth")
    try:
        install_test_protocol(tmp, mp, DEPTH_PROTOCOL)
        mp.setenv("SKYEYES_CACHE", str(tmp / "cache"))
        ds = open_dataset(synthtown_smoke)
        rng = np.random.default_rng(0)
        subs = {"gt": write_template(ds, tmp / "gt", from_ground_truth=True),
                "noise": _write(ds, tmp / "noise", lambda f: rng.random((f.height, f.width, 3)), "noise"),
                "grey": _write(ds, tmp / "grey", lambda f: np.full((f.height, f.width, 3), 0.5), "grey")}
        res = {k: evaluate(v, data=synthtown_smoke, out=tmp / f"{k}.json", progress=False) for k, v in subs.items()}
        yield ds, subs, res, tmp
    finally:
        mp.undo()


def test_new_submissions_are_scored_with_the_current_protocol_for_their_data(depth_scored):
    ds, subs, res, _ = depth_scored
    assert ds.protocol == "synthtown@1"
    assert res["gt"]["protocol"]["ref"] == "synthtown@9" and res["gt"]["submission"]["protocol"] == "synthtown@9"
    assert list(res["gt"]["metrics"]) == ["psnr", *SEQUENCE_METRICS]


def test_perfect_submission(depth_scored):
    _, _, res, _ = depth_scored
    m = res["gt"]["metrics"]
    assert m["psnr_seen"]["value"] == math.inf and m["psnr_unseen"]["value"] == math.inf
    assert m["ssim_seen"]["value"] == pytest.approx(1.0, abs=1e-12)
    assert m["ssim_unseen"]["value"] == pytest.approx(1.0, abs=1e-12)
    # the warp error of the ground truth is the floor, exactly
    assert m["warp"]["value"] == m["warp_floor"]["value"] and 0 < m["warp"]["value"] < 0.05
    assert m["warp_floor"]["reference"] is True and m["unseen_share"]["reference"] is True
    share = m["unseen_share"]["value"]
    assert 0.05 < share < 0.95  # the smoke lane has both
    for name in ("lpips_seen", "lpips_unseen"):
        assert m[name]["status"] == "unavailable" and m[name]["fix"] == "skyeyes-bench weights fetch"
    # the pooled pixels add up: seen + unseen = every pixel of every frame
    n_px = sum(f.width * f.height for _, f in expected_frames(open_dataset(res["gt"]["dataset"]["root"])))
    assert m["psnr_seen"]["pixels"] + m["psnr_unseen"]["pixels"] == n_px
    assert m["psnr_unseen"]["pixels"] / n_px == pytest.approx(share, rel=1e-12)


def test_frame_records_and_sequences(depth_scored):
    _, _, res, _ = depth_scored
    r = res["noise"]
    by_seq = {}
    for rec in r["frames"]:
        by_seq.setdefault(rec["sequence"], []).append(rec)
    for recs in by_seq.values():
        last = max(recs, key=lambda x: x["index"])
        assert last["warp"] is None and last["warp_n"] == 0  # no frame t + 1
        assert all(x["warp_n"] > 0 for x in recs if x is not last)
        for x in recs:
            assert x["psnr_seen_n"] + x["psnr_unseen_n"] == 48 * 48
            assert x["unseen_share"] == pytest.approx(x["psnr_unseen_n"] / (48 * 48))
            assert x["ssim_seen_n"] + x["ssim_unseen_n"] == 38 * 38  # the SSIM map's window centres
    for sid, v in r["sequences"].items():
        # independent noise: E|x - y| = 1/3 (less after bilinear resampling); the floor of this
        # aliased 48x48 data (one ray per pixel) is ~0.05
        assert v["warp"] > 0.2 and v["warp_floor"] < 0.1 and v["warp"] > 3 * v["warp_floor"]
    # the pooled value, written out
    w = np.array([x["psnr_seen_n"] for x in r["frames"]], float)
    mse = np.array([10 ** (-x["psnr_seen"] / 10) if x["psnr_seen_n"] else 0.0 for x in r["frames"]])
    assert r["metrics"]["psnr_seen"]["value"] == pytest.approx(-10 * np.log10((w * mse).sum() / w.sum()), rel=1e-12)
    assert r["metrics"]["psnr_seen"]["interval"] is not None and len(r["metrics"]["warp"]["replicates"]) == 200
    doc, _ = read_results(depth_scored[3] / "noise.json")  # nulls and pixel counts pass the reader
    assert doc["metrics"]["unseen_share"]["value"] == res["gt"]["metrics"]["unseen_share"]["value"]


def test_old_submission_rescored_with_a_later_protocol(depth_scored, synthtown_smoke, tmp_path):
    ds, subs, res, tmp = depth_scored
    # a submission written for the data's own protocol (what synthtown@2 submissions are to synthtown@3)
    old = tmp_path / "old"
    shutil.copytree(subs["grey"], old)
    man = json.loads((old / "submission.json").read_text())
    man.update(protocol="synthtown@1", protocol_sha256=None)
    (old / "submission.json").write_text(json.dumps(man))
    again = evaluate(old, data=synthtown_smoke, protocol="synthtown@9", progress=False)
    assert again["protocol"]["ref"] == "synthtown@9" and again["submission"]["protocol"] == "synthtown@1"
    for name in SEQUENCE_METRICS:
        assert again["metrics"][name].get("value") == res["grey"]["metrics"][name].get("value")
    # the CLI spelling; and a protocol that scores other data is refused in one line
    rc, out, err = run_cli("evaluate", "--allow-missing", str(old), "--data", str(synthtown_smoke), "--protocol", "synthtown@9",
                           "--out", str(tmp_path / "r.json"))
    assert "psnr_seen" in out and "warp_floor" in out and "of the ground truth: not a score" in out
    rc, out, err = run_cli("evaluate", "--allow-missing", str(old), "--data", str(synthtown_smoke), "--protocol", "synthtown@2",
                           "--out", str(tmp_path / "r2.json"), check=2)
    assert "field 'protocol' is 'synthtown@1', the evaluation uses 'synthtown@2'" in err


def test_submission_scored_with_an_earlier_version_of_the_same_data(depth_scored, synthtown_smoke, tmp_path):
    """A submission written for a later version (synthtown@10 here, as synthtown@4 is to
    synthtown@3) is scored by an earlier one that scores the same data, with that one's numbers;
    its protocol_sha256 is checked against the later file, and other data is still refused."""
    from skyeyes_bench.protocol import load_protocol

    ds, subs, res, tmp = depth_scored
    v10 = tmp / "protocols" / "synthtown" / "v10.toml"
    v10.write_text(DEPTH_PROTOCOL.replace("version = 9", "version = 10"))
    try:
        later = tmp_path / "later"
        shutil.copytree(subs["noise"], later)
        man = json.loads((later / "submission.json").read_text())
        man.update(protocol="synthtown@10", protocol_sha256=load_protocol("synthtown@10").sha256)
        (later / "submission.json").write_text(json.dumps(man))
        again = evaluate(later, data=synthtown_smoke, protocol="synthtown@9", progress=False)
        assert again["protocol"]["ref"] == "synthtown@9" and again["submission"]["protocol"] == "synthtown@10"
        for name in ("psnr", *SEQUENCE_METRICS):
            assert again["metrics"][name].get("value") == res["noise"]["metrics"][name].get("value"), name
        # a changed protocol file is caught against the version the submission names
        man.update(protocol_sha256="0" * 64)
        (later / "submission.json").write_text(json.dumps(man))
        rc, out, err = run_cli("evaluate", "--allow-missing", str(later), "--data", str(synthtown_smoke), "--protocol", "synthtown@9",
                               "--out", str(tmp_path / "r.json"), check=2)
        assert "'protocol_sha256' does not match protocol synthtown@10" in err
        # a version that scores other data (synthtown@2: synthtown-v2-small) refuses it
        man.update(protocol_sha256=load_protocol("synthtown@10").sha256)
        (later / "submission.json").write_text(json.dumps(man))
        rc, out, err = run_cli("evaluate", "--allow-missing", str(later), "--data", str(synthtown_smoke), "--protocol", "synthtown@2",
                               "--out", str(tmp_path / "r2.json"), check=2)
        assert "field 'protocol' is 'synthtown@10', the evaluation uses 'synthtown@2'" in err
    finally:
        v10.unlink()


def test_shards_merge_to_the_unsharded_numbers(depth_scored, synthtown_smoke, tmp_path):
    _, subs, res, _ = depth_scored
    parts = [tmp_path / f"p{i}.json" for i in range(3)]
    for i, p in enumerate(parts):
        evaluate(subs["noise"], data=synthtown_smoke, out=p, shard=(i, 3), progress=False)
    merged = merge(parts, progress=False)
    for name in SEQUENCE_METRICS:
        a, b = merged["metrics"][name], res["noise"]["metrics"][name]
        assert a.get("value") == b.get("value") and a.get("replicates") == b.get("replicates")


def test_compare_skips_reference_metrics_and_pools_pixels(depth_scored):
    _, _, res, _ = depth_scored
    out = compare_results(res["grey"], res["noise"], emcee_steps=300)
    m = out["metrics"]
    for name in ("unseen_share", "warp_floor"):
        assert m[name]["status"] == "skipped" and "property of the ground truth" in m[name]["note"]
    for name in ("psnr_seen", "psnr_unseen", "ssim_seen", "ssim_unseen", "warp"):
        assert m[name]["status"] == "ok"
        assert m[name]["advantage"] == pytest.approx(
            (1 if m[name]["higher_is_better"] else -1) * (m[name]["a"] - m[name]["b"]), abs=1e-12)
    assert m["warp"]["advantage"] > 0.2 and m["warp"]["bootstrap_interval"][0] > 0  # grey frames are consistent


def test_leaderboard_shows_reference_metrics_once(depth_scored, tmp_path):
    from skyeyes_bench.leaderboard import load_tables
    from skyeyes_bench.leaderboard.render import render_markdown

    _, _, res, tmp = depth_scored
    (tmp_path / "results").mkdir()
    (tmp_path / "reported").mkdir()
    for k in ("gt", "noise", "grey"):
        shutil.copy(tmp / f"{k}.json", tmp_path / "results" / f"{k}.json")
    measured, _ = load_tables(tmp_path)
    (t,) = measured
    assert "unseen_share" not in t.metrics and "warp_floor" not in t.metrics and "warp" in t.metrics
    share = res["gt"]["metrics"]["unseen_share"]["value"]
    assert f"of the ground truth, the same for every row: Unseen share {share:.3f}, Warp floor" in t.note
    page = render_markdown(tmp_path, measured, [], [], {})
    assert "Warp error ↓" in page and "PSNR unseen ↑" in page and "Unseen share ↓" not in page


def test_missing_depth_layers_make_only_their_metrics_unavailable(depth_scored, synthtown_smoke, tmp_path):
    _, subs, res, _ = depth_scored
    data = tmp_path / "no-aerial-depth"
    shutil.copytree(synthtown_smoke, data)
    for scene in data.iterdir():
        if (scene / "aerial_depth").is_dir():
            shutil.rmtree(scene / "aerial_depth")
    out = evaluate(subs["grey"], data=data, progress=False)["metrics"]
    for name in ("psnr_seen", "ssim_unseen", "unseen_share", "lpips_seen"):
        assert out[name]["status"] == "unavailable"
        assert out[name]["reason"].startswith("the dataset has no depth layer test-0-lane00/aerial_depth/")
    assert out["warp"]["value"] == res["grey"]["metrics"]["warp"]["value"]  # needs ground depth only
    assert out["psnr"]["value"] == res["grey"]["metrics"]["psnr"]["value"]
