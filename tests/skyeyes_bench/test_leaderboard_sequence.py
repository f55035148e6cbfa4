"""The leaderboard's test sequence (issue 36): `leaderboard add` saves one fixed test sequence of
each submission (and once of the ground truth) as an animated WebP, the page build draws one
composite animation per table with every row in step, and `--check` compares it.

Checked against an independent computation: the animations are decoded here with Pillow alone
(durations expanded to 125 ms steps) and compared with the frame files of the submission and the
dataset; a submission whose frame i is 20 + 10 i levels brighter shows that order survives."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from conftest import ROOT, run_cli
from builders.evaluation import blurred_submission, indexed_submission, make_dataset, protocol_env

from skyeyes_bench import leaderboard
from skyeyes_bench.leaderboard import plots, sequence

#: Mean |decoded - frame| (8-bit levels) a lossy WebP may add to a 32 px frame of the test data.
#: Measured here: at most 7.6 for the ground truth (random fine texture, the hardest case: 2.9 on
#: synthtown frames), 3.9 for 'indexed', 4.7 for 'blurry'; the composite re-encodes a decoded row,
#: at most 9.1. Another frame of the same row is at least 13.8 away, so order is checked apart.
ROW_MAE, COMPOSITE_MAE = 10.0, 12.0
FRAMES = 16  # frames per sequence of the test dataset


def _decode(path: Path) -> list[np.ndarray]:
    """Every 125 ms step of an animated WebP, decoded with Pillow alone (uint8 [H, W, 3])."""
    im = Image.open(path)
    assert im.format == "WEBP"
    out = []
    for i in range(im.n_frames):
        im.seek(i)
        im.load()
        out += [np.asarray(im.convert("RGB"))] * round(im.info["duration"] / 125)
    return out


def _read(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"))


def _mae(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a.astype(float) - b.astype(float)).mean())


@pytest.fixture(scope="module")
def board(tmp_path_factory):
    """A 3-scene dataset; 'indexed' (frame i brightened by 20 + 10 i levels) and 'blurry' filed
    with their frames; 'gone' filed from a submission that is no longer on the machine."""
    tmp = tmp_path_factory.mktemp("lbseq")
    with protocol_env(tmp) as mp:
        from skyeyes_bench.data.layout import open_dataset
        from skyeyes_bench.evaluate import evaluate

        ds = open_dataset(make_dataset(tmp / "ds", scenes=3, seqs=2, frames=FRAMES))
        root = tmp / "leaderboard"
        shutil.copytree(ROOT / "leaderboard" / "reported", root / "reported")
        outs = {}
        indexed_submission(ds, tmp / "indexed")
        blurred_submission(ds, tmp / "blurry", sigma=1.5, method="blurry")
        for name in ("indexed", "blurry"):
            evaluate(tmp / name, data=ds.root, out=tmp / f"{name}.results.json", progress=False)
            outs[name] = run_cli("leaderboard", "add", str(tmp / f"{name}.results.json"), "--root", str(root))[1]
        doc = json.loads((tmp / "blurry.results.json").read_text())
        doc["submission"].update(path=str(tmp / "no-longer-here"), method="gone")
        (tmp / "gone.results.json").write_text(json.dumps(doc))
        outs["gone"] = run_cli("leaderboard", "add", str(tmp / "gone.results.json"), "--root", str(root),
                               "--name", "gone")[1]
        run_cli("leaderboard", "--root", str(root))
        (key,) = [p.name for p in (root / "frames").iterdir()]
        yield {"root": root, "tmp": tmp, "ds": Path(ds.root), "outs": outs, "frames": root / "frames" / key, "mp": mp}


def test_the_sequence_is_the_first_strip_frames_whole_sequence(board):
    doc = json.loads((board["tmp"] / "indexed.results.json").read_text())
    listed = json.loads((board["frames"] / "frames.json").read_text())
    first = listed["frames"][0]
    # independent: the records of the first strip frame's sequence, in index order
    q = next(r["sequence"] for r in doc["frames"] if (r["scene"], r["file"]) == (first["scene"], first["file"]))
    want = sorted((r for r in doc["frames"] if r["sequence"] == q), key=lambda r: r["index"])
    seq = listed["sequence"]
    assert seq["sequence"] == first["sequence"] == doc["dataset"]["sequences"][q] and seq["scene"] == first["scene"]
    assert [(f["file"], f["index"]) for f in seq["frames"]] == [(r["file"], r["index"]) for r in want]
    assert len(seq["frames"]) == FRAMES and seq["label"] == f"{seq['sequence']} #0–#{FRAMES - 1}"
    assert leaderboard.choose_sequence(doc, listed["frames"]) == seq


def test_add_saves_each_rows_frames_in_order(board):
    seq = json.loads((board["frames"] / "frames.json").read_text())["sequence"]
    sub = [_read(board["tmp"] / "indexed" / seq["scene"] / f["file"]) for f in seq["frames"]]
    got = _decode(board["frames"] / "indexed" / "sequence.webp")
    assert len(got) == FRAMES and got[0].shape == sub[0].shape == (32, 32, 3)
    for k, g in enumerate(got):
        assert _mae(g, sub[k]) < ROW_MAE, k
        assert int(np.argmin([_mae(g, s) for s in sub])) == k  # its own frame is the nearest: order kept
    means = [g.mean() for g in got]
    assert all(b - a > 5 for a, b in zip(means, means[1:]))  # 10 levels brighter each step
    truth = [_read(board["ds"] / seq["scene"] / f["file"]) for f in seq["frames"]]
    gt = _decode(board["frames"] / "ground-truth" / "sequence.webp")
    assert len(gt) == FRAMES and max(_mae(g, t) for g, t in zip(gt, truth)) < ROW_MAE
    out = board["outs"]["indexed"]
    assert f"sequence: {FRAMES} frames of {seq['sequence']} saved to" in out and "ground truth saved" in out
    assert "ground truth saved" not in board["outs"]["blurry"]  # once per protocol and dataset
    assert (board["frames"] / "indexed" / "sequence.webp").stat().st_size < 150_000


def test_no_animation_when_the_submission_is_missing(board):
    assert "sequence: no animation for gone" in board["outs"]["gone"]
    assert not (board["frames"] / "gone").exists()
    md = (board["root"] / "README.md").read_text()
    assert "No saved sequence for: gone (filed before" in md
    html = (board["root"] / "index.html").read_text()
    assert "No saved sequence for: gone (filed before <code>leaderboard add</code>" in html


def test_composite_shows_ground_truth_then_each_row_in_step(board):
    root = board["root"]
    seq = json.loads((board["frames"] / "frames.json").read_text())["sequence"]
    got = _decode(root / "strips" / "evaltest@1-sequence.webp")
    T, L, G = plots.TILE, sequence.LABEL_H, sequence.GAP
    # ground truth, blurry, indexed (the table's order); gone has no saved sequence
    assert len(got) == FRAMES and got[0].shape == (L + T, 3 * T + 2 * G, 3)

    def tile(frame, j):
        return frame[L:L + T, j * (T + G):j * (T + G) + T]

    def big(p):  # 32 px frames enlarged 4x (nearest), as the composite shows them
        return np.repeat(np.repeat(_read(p), 4, axis=0), 4, axis=1)

    truth = [big(board["ds"] / seq["scene"] / f["file"]) for f in seq["frames"]]
    blurry = [big(board["tmp"] / "blurry" / seq["scene"] / f["file"]) for f in seq["frames"]]
    indexed = [big(board["tmp"] / "indexed" / seq["scene"] / f["file"]) for f in seq["frames"]]
    for k, g in enumerate(got):
        assert _mae(tile(g, 0), truth[k]) < COMPOSITE_MAE, k
        assert _mae(tile(g, 1), blurry[k]) < COMPOSITE_MAE, k
        assert _mae(tile(g, 2), indexed[k]) < COMPOSITE_MAE, k
        assert int(np.argmin([_mae(tile(g, 2), s) for s in indexed])) == k  # in step with the ground truth
    for j in range(3):  # a name is drawn above each tile
        assert (got[0][:L, j * (T + G):j * (T + G) + T] < 128).any(), j
    md, html = (root / "README.md").read_text(), (root / "index.html").read_text()
    assert "](strips/evaltest@1-sequence.webp)" in md and 'src="strips/evaltest@1-sequence.webp"' in html
    assert f"Animation: test sequence {seq['label']} ({FRAMES} frames at 8 per second" in html


def test_regeneration_is_deterministic_and_check_compares_the_animation(board, tmp_path):
    root = tmp_path / "lb"
    shutil.copytree(board["root"], root)
    name = "strips/evaltest@1-sequence.webp"
    a, b = leaderboard.build(root), leaderboard.build(root)
    assert a[name] == b[name] and a == b
    assert (root / name).read_bytes() == a[name]
    run_cli("leaderboard", "--root", str(root), "--check")
    # other bytes from this encoder (with no provenance, or even claiming the same inputs): stale
    frames = sequence.decode_webp(a[name], "composite")
    inputs, here = sequence.provenance(a[name])
    assert here == sequence.encoder() and len(inputs) == 64
    for enc in (None, here):
        exif = enc and {sequence._INPUTS_TAG: sequence._INPUTS + inputs, sequence._ENCODER_TAG: enc}
        (root / name).write_bytes(sequence.encode_webp(frames, (20,), 10**9, exif=exif))
        rc, out, err = run_cli("leaderboard", "--root", str(root), "--check", check=1)
        assert f"{name} (differs)" in err
    # another encoder: other pixels for the same inputs, its own name in the EXIF: up to date
    exif = {sequence._INPUTS_TAG: sequence._INPUTS + inputs, sequence._ENCODER_TAG: "Pillow 0.0, libwebp 0.0"}
    (root / name).write_bytes(sequence.encode_webp(frames, (20,), 10**9, exif=exif))
    run_cli("leaderboard", "--root", str(root), "--check")
    # ... unless its inputs were other: a row's saved sequence replaced
    frames_dir = next((root / "frames").iterdir())
    shutil.copy(frames_dir / "blurry" / "sequence.webp", frames_dir / "indexed" / "sequence.webp")
    rc, out, err = run_cli("leaderboard", "--root", str(root), "--check", check=1)
    assert f"{name} (differs)" in err
    # a stale animation is reported and removed
    run_cli("leaderboard", "--root", str(root))
    (root / "strips" / "old-sequence.webp").write_bytes(b"x")
    rc, out, err = run_cli("leaderboard", "--root", str(root), "--check", check=1)
    assert "strips/old-sequence.webp (no longer generated)" in err
    run_cli("leaderboard", "--root", str(root))
    assert not (root / "strips" / "old-sequence.webp").exists()


def _legacy(board, tmp_path) -> Path:
    """A leaderboard as filed before sequences were saved: 'blurry' with its strip frames, a
    frames.json without a sequence, no sequence.webp anywhere."""
    root = tmp_path / "lb"
    shutil.copytree(board["root"], root, ignore=shutil.ignore_patterns("indexed*", "gone*", "*.webp"))
    listed = next((root / "frames").iterdir()) / "frames.json"
    raw = json.loads(listed.read_text())
    del raw["sequence"]
    listed.write_text(json.dumps(raw, indent=2) + "\n")
    run_cli("leaderboard", "--root", str(root))
    return root


def test_a_list_from_before_sequences_gets_one_and_old_rows_say_so(board, tmp_path):
    root = _legacy(board, tmp_path)
    assert "No sequence animation yet: no saved sequence for: ground truth, blurry" in (root / "README.md").read_text()
    assert not (root / "strips" / "evaltest@1-sequence.webp").exists()
    listed = next((root / "frames").iterdir()) / "frames.json"
    before = json.loads(listed.read_text())
    rc, out, err = run_cli("leaderboard", "add", str(board["tmp"] / "indexed.results.json"), "--root", str(root))
    after = json.loads(listed.read_text())
    assert after["frames"] == before["frames"]  # the strip frames stay
    assert after["sequence"] == json.loads((board["frames"] / "frames.json").read_text())["sequence"]
    assert "sequence: ground truth saved" in out and (listed.parent / "ground-truth" / "sequence.webp").is_file()
    run_cli("leaderboard", "--root", str(root))
    md = (root / "README.md").read_text()
    assert "](strips/evaltest@1-sequence.webp)" in md and "No saved sequence for: blurry (filed before" in md
    assert len(_decode(root / "strips" / "evaltest@1-sequence.webp")) == FRAMES


def test_a_failed_add_restores_the_frames_list_it_extended(board, tmp_path, monkeypatch):
    root = _legacy(board, tmp_path)
    listed = next((root / "frames").iterdir()) / "frames.json"
    before = listed.read_bytes()
    from skyeyes_bench.errors import UserError
    from skyeyes_bench.leaderboard import add

    def fail(*a, **k):
        raise UserError("disk full (test)")

    monkeypatch.setattr(add, "write_results_file", fail)
    rc, out, err = run_cli("leaderboard", "add", str(board["tmp"] / "indexed.results.json"), "--root", str(root),
                           check=2)
    assert "disk full (test)" in err
    assert listed.read_bytes() == before
    assert not (listed.parent / "indexed").exists() and not (listed.parent / "ground-truth" / "sequence.webp").exists()


def test_decode_refuses_what_is_not_the_sequence_in_one_line():
    from skyeyes_bench.errors import UserError

    frames = [np.full((8, 8, 3), 10 * i, np.uint8) for i in range(4)]
    data = sequence.encode_webp(frames, (80,), 10**9)
    assert [f.mean() for f in sequence.decode_webp(data, "x", frames=4)] == pytest.approx([0, 10, 20, 30], abs=2)
    still = sequence.encode_webp([frames[1]] * 4, (80,), 10**9)  # identical frames: a still WebP
    assert len(sequence.decode_webp(still, "x", frames=4)) == 4
    for bad, why in ((b"GIF89a" + data, "not a WebP"), (data[:60], "cannot decode"), (data, "expected 5")):
        with pytest.raises(UserError, match=why) as e:
            sequence.decode_webp(bad, "x", frames=5 if why == "expected 5" else 4)
        assert "\n" not in str(e.value)
    with pytest.raises(UserError, match="at most 4 on a side"):
        sequence.decode_webp(data, "x", frames=4, max_side=4)
