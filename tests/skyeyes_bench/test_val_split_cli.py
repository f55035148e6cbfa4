"""A run on the validation split, the user's way (`reproduce --split val` in a process of its own,
smoke size, no extractor weights: the image metrics only): its submission and results say
`split: "val"` and hold the validation town's sequences; `evaluate --split test` refuses it,
`leaderboard add` never files it and `compare` never sets it beside test results."""

import json
import os
import shutil
import subprocess
import sys

import pytest
from conftest import ROOT, run_cli

#: The smoke preset's validation data: one lane of the town val-0, 8 yaws of 16 frames.
VAL_SEQUENCES = [f"val-0-lane00/yaw{45 * k:03d}" for k in range(8)]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """The output folder of `skyeyes-bench reproduce --method mean-frame --preset smoke --split val`."""
    tmp = tmp_path_factory.mktemp("val-run")
    env = {**os.environ, "SKYEYES_CACHE": str(tmp / "cache")}
    env.pop("SKYEYES_PROTOCOLS", None)
    out = tmp / "X"
    r = subprocess.run([sys.executable, "-m", "skyeyes_bench.cli", "reproduce", "--method", "mean-frame", "--preset",
                        "smoke", "--split", "val", "--out", str(out), "--quiet"], capture_output=True, text=True,
                       cwd=tmp, env=env, timeout=600)
    assert r.returncode == 0, f"rc={r.returncode}\nstdout:\n{r.stdout}\nstderr:\n{r.stderr}"
    assert "val split" in r.stdout  # the summary names the split
    return out, tmp / "cache"


@pytest.fixture
def cache(run, monkeypatch):
    """This test's in-process CLI sees the run's cache (its data)."""
    monkeypatch.setenv("SKYEYES_CACHE", str(run[1]))
    return run[1]


def _one_line_exit_2(*args) -> str:
    rc, out, err = run_cli(*args, check=None)
    assert rc == 2, f"rc={rc}\nstdout:\n{out}\nstderr:\n{err}"
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


def test_the_submission_and_results_say_val(run):
    out, cache = run
    sub = json.loads((out / "submission" / "submission.json").read_text())
    assert sub["dataset"]["split"] == "val"
    assert sub["dataset"]["name"] == "synthtown-smoke-val"
    assert sub["dataset"]["frames"] == 8 * 16
    res = json.loads((out / "results.json").read_text())
    assert res["dataset"]["split"] == "val"
    assert res["dataset"]["name"] == "synthtown-smoke-val"
    assert res["dataset"]["sequences"] == VAL_SEQUENCES
    assert sorted({f["scene"] for f in res["frames"]}) == ["val-0-lane00"]
    assert len(res["frames"]) == 8 * 16
    assert res["metrics"]["psnr"]["status"] == "ok"
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["dataset"]["split"] == "val" and "--split val" in cfg["repeat"]
    assert cfg["dataset"]["root"] == str(cache / "data" / "synthtown-smoke-val")
    # the submission holds the validation town's frames and nothing of the test town
    assert sorted(p.name for p in (out / "submission").iterdir() if p.is_dir()) == ["val-0-lane00"]


def test_evaluate_scores_the_split_the_submission_holds(run, cache, tmp_path):
    out, _ = run
    err = _one_line_exit_2("evaluate", "--allow-missing", str(out / "submission"), "--split", "test")
    assert "dataset.split" in err and "'val'" in err and "'test'" in err
    for extra in ([], ["--split", "val"]):
        dest = tmp_path / f"r{len(extra)}.json"
        run_cli("evaluate", "--allow-missing", str(out / "submission"), "--out", str(dest), "--quiet", *extra)
        doc = json.loads(dest.read_text())
        assert doc["dataset"]["split"] == "val" and doc["dataset"]["sequences"] == VAL_SEQUENCES


def _test_split_twin(run, tmp_path):
    """A copy of the run's results.json (and its features sidecar) that says split "test": the
    only difference from the val results."""
    out, _ = run
    doc = json.loads((out / "results.json").read_text())
    doc["dataset"]["split"] = "test"
    twin = tmp_path / "twin.json"
    twin.write_text(json.dumps(doc))
    side = out / "results.features.npz"
    if side.exists():
        shutil.copy(side, tmp_path / "twin.features.npz")
    return twin


def test_leaderboard_add_refuses_val_results(run, cache, tmp_path):
    out, _ = run
    lb = tmp_path / "lb"
    shutil.copytree(ROOT / "leaderboard" / "reported", lb / "reported")
    (lb / "results").mkdir()
    err = _one_line_exit_2("leaderboard", "add", str(out / "results.json"), "--root", str(lb))
    assert "dataset.split" in err and "'val'" in err and str(out / "results.json") in err
    assert not list((lb / "results").iterdir())
    # the same file saying "test" is not refused for its split
    twin = _test_split_twin(run, tmp_path)
    rc, _, err = run_cli("leaderboard", "add", str(twin), "--root", str(lb), check=None)
    assert "dataset.split" not in err, err


def test_compare_refuses_val_against_test(run, cache, tmp_path):
    out, _ = run
    twin = _test_split_twin(run, tmp_path)
    for a, b, sa, sb in ((out / "results.json", twin, "val", "test"), (twin, out / "results.json", "test", "val")):
        err = _one_line_exit_2("compare", str(a), str(b))
        assert f"A was scored on the {sa} split, B on the {sb} split" in err, err
    # the run against itself compares
    run_cli("compare", str(out / "results.json"), str(out / "results.json"), "--json")
