"""Issue 35: `compare` and `merge` against edited results and parts. Every case exits 2 with one
line (naming the file and the frame or field), no traceback, and `merge` writes nothing; values
near float64's limits are compared without a traceback or a numpy warning.

The cases edit copies of valid files (two results of one dataset, and the two shard parts of
the first), one edit each, so a case that passes for the wrong reason would show as a valid
file being refused in `test_unedited_files_compare_and_merge`.
"""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from builders.evaluation import blurred_submission, make_dataset, protocol_env
from conftest import run_cli

from skyeyes_bench import inputfiles

IMAGE_EX = "random-image-64"


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """a.json, b.json: two submissions of one dataset (3 scenes x 2 sequences x 4 frames, K = 6
    sequences: intervals and Student-t fits); p0.json, p1.json: the shards 0/2 and 1/2 of a."""
    from skyeyes_bench.data.layout import open_dataset
    from skyeyes_bench.evaluate import evaluate

    tmp = tmp_path_factory.mktemp("cmw")
    with protocol_env(tmp):
        ds = open_dataset(make_dataset(tmp / "ds", scenes=3, seqs=2, frames=4))
        sub_a = blurred_submission(ds, tmp / "sub-a", sigma=0.7, method="a")
        sub_b = blurred_submission(ds, tmp / "sub-b", sigma=1.5, method="b")
        evaluate(sub_a, data=tmp / "ds", out=tmp / "a.json", progress=False)
        evaluate(sub_b, data=tmp / "ds", out=tmp / "b.json", progress=False)
        for i in (0, 1):
            evaluate(sub_a, data=tmp / "ds", out=tmp / f"p{i}.json", shard=f"{i}/2", progress=False)
        yield tmp


@pytest.fixture
def w(world, tmp_path, monkeypatch):
    """A fresh copy of the world's files for one case (the protocol installed as it was)."""
    monkeypatch.setenv("SKYEYES_PROTOCOLS", str(world / "protocols"))
    for n in ("a", "b", "p0", "p1"):
        shutil.copy(world / f"{n}.json", tmp_path)
        shutil.copy(world / f"{n}.features.npz", tmp_path)
    return tmp_path


def _edit(path: Path, fn) -> None:
    doc = json.loads(path.read_text())
    fn(doc)
    path.write_text(json.dumps(doc))


def _edit_sidecar(path: Path, fn) -> None:
    """Change the features sidecar of `path` and record its new sha256 (so only `fn` differs)."""
    side = path.with_name(path.name[: -len(".json")] + ".features.npz")
    with np.load(side) as z:
        arrays = {k: z[k].copy() for k in z.files}
    fn(arrays)
    with open(side, "wb") as fh:
        np.savez(fh, **arrays)
    _edit(path, lambda d: d["features"].__setitem__("sha256", inputfiles.sha256_file(side)))


def _one_line_exit_2(args, *wants):
    rc, out, err = run_cli(*args, check=None)
    assert rc == 2, f"rc={rc}\nstdout:\n{out}\nstderr:\n{err}"
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("skyeyes-bench: error: "), err
    assert "Traceback" not in err and not out, (out, err)
    for want in wants:
        assert want in lines[0], f"{want!r} not in: {lines[0]}"
    return lines[0]


def _set(path: list, value):
    def fn(doc):
        node = doc
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value
    return fn


def _frame3(doc):
    return doc["frames"][3]


FRAME3 = "test-0-lane00/ground/000003.png"  # frames are sorted: the 4th of the first sequence

# --------------------------------------------------------------------------- compare

#: name -> (edit of b.json, fragments the one line must hold; "{b}" is b.json's path)
COMPARE_CASES = {
    "renamed-frame": (lambda d: _frame3(d).__setitem__("file", "ground/renamed.png"), ["{b}", FRAME3, "renamed"]),
    "missing-frame": (lambda d: d["frames"].pop(3), ["{b}", FRAME3, "missing"]),
    "no-frames": (lambda d: d.__setitem__("frames", []), ["{b}", "(and 23 more)"]),
    "frame-twice": (lambda d: d["frames"].append(d["frames"][0]), ["{b}", "frames[24]", "listed twice"]),
    "frame-of-another-sequence": (lambda d: _frame3(d).__setitem__("sequence", 1),
                                  ["{b}", FRAME3, "'test-0-lane00/yaw090'"]),
    "frame-of-other-ground-truth": (lambda d: _frame3(d).__setitem__("gt_sha256", "0" * 64),
                                    ["{b}", FRAME3, "other ground truth"]),
    "frames-without-a-metric": (lambda d: [r.pop("ssim") for r in d["frames"]], ["{b}", "frames[0].ssim", "missing"]),
    "statistics-a-list": (_set(["statistics"], [1]), ["{b}", "field 'statistics'", "an object"]),
    "statistics-a-string": (_set(["statistics"], "half"), ["{b}", "field 'statistics'"]),
    "nan-value": (_set(["metrics", "ssim", "value"], float("nan")), ["{b}", "metrics.ssim.value", "NaN"]),
    "nan-interval": (_set(["metrics", "fid", "interval"], [float("nan"), 1.0]), ["{b}", "metrics.fid.interval[0]"]),
    "nan-replicate": (lambda d: d["metrics"]["fid"]["replicates"].__setitem__(7, float("nan")),
                      ["{b}", "metrics.fid.replicates[7]", "NaN"]),
    "nan-frame-value": (lambda d: _frame3(d).__setitem__("psnr", float("nan")), ["{b}", "frames[3].psnr", "NaN"]),
    "nan-sequence-value": (_set(["sequences", "test-0-lane01/yaw000", "ssim"], float("nan")),
                           ["{b}", "sequences.test-0-lane01/yaw000.ssim"]),
    "unknown-metric-without-frames": (lambda d: (d["metrics"].__setitem__("zeta", {"status": "ok", "kind": "frame",
                                                                                    "value": 1.0}),
                                                 [s.__setitem__("zeta", 1.0) for s in d["sequences"].values()]),
                                      ["{b}", "frames[0].zeta", "missing"]),
    "protocol-sha256-edited": (_set(["protocol", "sha256"], "f" * 64), ["differs between A and B", "ffffffffffff"]),
    "frame-name-with-newline": (lambda d: _frame3(d).__setitem__("file", "ground/x\ny.png"), ["{b}", FRAME3]),
    "protocol-ref-with-newline": (_set(["protocol", "ref"], "evaltest@1\nevaltest@2"), ["evaltest@1\\nevaltest@2"]),
    "protocol-sha256-with-bidi-override": (_set(["protocol", "sha256"], "\u202e" + "e" * 63), ["\\u202eeeeeeeeeeee"]),
}


@pytest.mark.parametrize("case", sorted(COMPARE_CASES))
def test_compare_of_edited_results(w, case):
    edit, wants = COMPARE_CASES[case]
    _edit(w / "b.json", edit)
    _one_line_exit_2(["compare", str(w / "a.json"), str(w / "b.json")], *(x.format(b=w / "b.json") for x in wants))
    # the edited file as A: refused and named as well
    _one_line_exit_2(["compare", str(w / "b.json"), str(w / "a.json")], *[str(w / "b.json")] * ("{b}" in wants))


def test_compare_names_control_characters_escaped(w):
    """An extractor id both files hold, with control characters: the line that refuses them stays one line."""
    for n, sha in (("a", "1" * 64), ("b", "2" * 64)):
        _edit(w / f"{n}.json", lambda d, sha=sha: d["extractors"].__setitem__(
            "x\r\x1b[2K\u202e", {"kind": "image", "dim": 1, "weights_sha256": sha, "status": "ok"}))
    _one_line_exit_2(["compare", str(w / "a.json"), str(w / "b.json")],
                     "extractor x\\r\\x1b[2K\\u202e used different weights")


def test_compare_of_results_scored_under_another_file_of_the_protocol(w, world, tmp_path_factory, monkeypatch):
    """Both results agree on their protocol's sha256, the installed evaltest/v1.toml does not."""
    from builders.evaluation import TEST_PROTOCOL

    other = tmp_path_factory.mktemp("other-protocols")
    shutil.copytree(world / "protocols", other / "protocols")
    (other / "protocols" / "evaltest" / "v1.toml").write_text(TEST_PROTOCOL.replace("seed = 0", "seed = 2"))
    monkeypatch.setenv("SKYEYES_PROTOCOLS", str(other / "protocols"))
    _one_line_exit_2(["compare", str(w / "a.json"), str(w / "b.json")], "changed since A and B were scored")


@pytest.mark.parametrize("value", [1e200, 1.5e308, -1.7e308])
def test_compare_of_values_near_the_float64_limit(w, value):
    """Per-frame values far beyond any metric's range (and replicates and values near float64's
    largest number): compared without a traceback or a numpy warning; the Student-t model is not
    fitted and says why."""
    def edit(d):
        for r in d["frames"]:
            r["ssim"] = value * (r["sequence"] + 1) / 8  # sequences differ: not a zero-variance case
        d["metrics"]["fid"]["value"] = abs(value)
        d["metrics"]["fid"]["replicates"] = [abs(value), -abs(value)] * (len(d["metrics"]["fid"]["replicates"]) // 2)
    _edit(w / "b.json", edit)
    rc, out, err = run_cli("compare", str(w / "a.json"), str(w / "b.json"), "--json", check=0)
    assert "Traceback" not in err and "Warning" not in err.replace("skyeyes-bench: warning:", ""), err
    res = json.loads(out)
    bz = res["metrics"]["ssim"]["bayes"]
    assert not bz["fitted"]
    if abs(value) < 1e300:  # finite per-sequence differences too large for the model
        assert "exceeds 1e+12" in bz["note"] and bz["p_a_better"] is None
    rc, text, err = run_cli("compare", str(w / "a.json"), str(w / "b.json"), check=0)
    assert "Traceback" not in err and "Warning" not in err.replace("skyeyes-bench: warning:", ""), err


# --------------------------------------------------------------------------- merge

#: name -> (edit of p1.json, fragments the one line must hold; "{p}" is p1.json's path)
MERGE_CASES = {
    "renamed-frame": (lambda d: d["frames"][0].__setitem__("file", "ground/renamed.png"),
                      ["{p}", "frames[0]", "renamed.png", "no such frame in the submission"]),
    "edited-sha256": (lambda d: d["frames"][0].__setitem__("sha256", "0" * 64),
                      ["{p}", "frames[0]", "000000000000... recorded", "edited"]),
    "record-removed": (lambda d: d["frames"].pop(0), ["{p}", "3 records of sequence 'test-0-lane00/yaw090'",
                                                      "features of 4"]),
    "record-twice": (lambda d: d["frames"].append(d["frames"][0]), ["{p}", "listed twice"]),
    "record-of-the-other-shard": (lambda d, p0: d["frames"].append(p0["frames"][0]),
                                  ["{p}", "frames[12]", "'test-0-lane00/yaw000', which shard 1/2 does not score"]),
    "record-also-in-the-other-part": (lambda d, p0: d["frames"].__setitem__(0, {**p0["frames"][0], "sequence": 1}),
                                      ["{p}", "frames[0]", "also in {p0}"]),
    "record-in-another-scene": (lambda d: d["frames"][0].__setitem__("scene", "test-0-lane09"),
                                ["{p}", "frames[0]", "not in scene 'test-0-lane00'"]),
    "record-without-a-metric": (lambda d: d["frames"][5].pop("psnr"), ["{p}", "frames[5].psnr", "missing"]),
    "nan-frame-value": (lambda d: d["frames"][5].__setitem__("ssim", float("nan")), ["{p}", "frames[5].ssim", "NaN"]),
    "unavailable-without-reason": (_set(["unavailable", "lpips"], {}), ["{p}", "unavailable.lpips.reason"]),
}


@pytest.mark.parametrize("case", sorted(MERGE_CASES))
def test_merge_of_an_edited_part(w, case):
    edit, wants = MERGE_CASES[case]
    p0 = json.loads((w / "p0.json").read_text())
    _edit(w / "p1.json", (lambda d: edit(d, p0)) if edit.__code__.co_argcount == 2 else edit)
    out = w / "merged.json"
    _one_line_exit_2(["merge", str(w / "p0.json"), str(w / "p1.json"), "--out", str(out), "--quiet"],
                     *(x.format(p=w / "p1.json", p0=w / "p0.json") for x in wants))
    assert not out.exists() and not (w / "merged.features.npz").exists()


def test_merge_of_an_edited_part_whose_submission_is_elsewhere(w):
    """The submission folder is not on this machine: the edit is found by the digest and the
    line names the parts (one of them was edited)."""
    gone = str(w / "not-here")
    for n in ("p0", "p1"):
        _edit(w / f"{n}.json", _set(["submission", "path"], gone))
    _edit(w / "p1.json", lambda d: d["frames"][0].__setitem__("sha256", "0" * 64))
    _one_line_exit_2(["merge", str(w / "p0.json"), str(w / "p1.json"), "--out", str(w / "m.json"), "--quiet"],
                     "frame records of one of", str(w / "p0.json"), str(w / "p1.json"), "submission.frames_sha256")
    assert not (w / "m.json").exists()


#: name -> (edit of p1's sidecar arrays, fragments)
SIDECAR_CASES = {
    "nan-feature": (lambda a: a[f"{IMAGE_EX}|sub"].__setitem__((0, 0), np.nan), [f"'{IMAGE_EX}|sub'", "NaN"]),
    "inf-feature": (lambda a: a[f"{IMAGE_EX}|gt"].__setitem__((2, 5), np.inf), [f"'{IMAGE_EX}|gt'", "infinite"]),
    "rows-of-the-other-shard": (lambda a: a[f"{IMAGE_EX}|seq"].__setitem__(0, 0),
                                [f"'{IMAGE_EX}|seq'", "'test-0-lane00/yaw000', which shard 1/2 does not score"]),
}


@pytest.mark.parametrize("case", sorted(SIDECAR_CASES))
def test_merge_of_a_part_with_an_edited_sidecar(w, case):
    edit, wants = SIDECAR_CASES[case]
    _edit_sidecar(w / "p1.json", edit)
    _one_line_exit_2(["merge", str(w / "p0.json"), str(w / "p1.json"), "--out", str(w / "m.json"), "--quiet"],
                     "p1.features.npz", *wants)
    assert not (w / "m.json").exists()


def test_unedited_files_compare_and_merge(w):
    """The control: the files every case edits are valid as they are, and the merged frames'
    digest is the unsharded one (what the merge check recomputes)."""
    run_cli("compare", str(w / "a.json"), str(w / "b.json"), "--json")
    run_cli("merge", str(w / "p0.json"), str(w / "p1.json"), "--out", str(w / "m.json"), "--quiet")
    merged, full = (json.loads((w / f"{n}.json").read_text()) for n in ("m", "a"))
    assert merged["sha256"] == full["sha256"]
    assert merged["sha256"]["submission_frames"] == merged["submission"]["frames_sha256"]
