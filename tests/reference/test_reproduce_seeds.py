"""Issue 57: `reproduce --seeds N` end to end on the cheapest method (mean-frame, smoke): one
complete run per seed in its own folder, and a results.json that is the first seed's with a
`seeds` block of every seed's values, which `compare`, `read_results` and `leaderboard add` take."""

import json

import numpy as np
import pytest

from conftest import run_cli
from skyeyes_bench.results import features_path, read_results

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest: a second thread only spins here


def test_seeds_run_writes_every_seed_and_their_spread(synthtown_smoke, tmp_path):
    out = tmp_path / "mf"
    args = ["reproduce", "--method", "mean-frame", "--preset", "smoke", "--data", str(synthtown_smoke), "--out",
            str(out), "--seeds", "2", "--quiet"]
    _, text, _ = run_cli(*args)
    # 1. each seed a complete single-seed run in its own folder
    for s in (0, 1):
        cfg = json.loads((out / f"seed-{s}" / "config.json").read_text())
        assert cfg["seed"] == s and cfg["method"] == "mean-frame" and (out / f"seed-{s}" / "submission").is_dir()
    seeds = [json.loads((out / f"seed-{s}" / "results.json").read_text()) for s in (0, 1)]
    # 2. results.json: the first seed's results, intact, with the block; its sidecar beside it
    top = json.loads((out / "results.json").read_text())
    block = top.pop("seeds")
    assert top == seeds[0]
    sidecar = features_path(out / "results.json")
    assert sidecar.read_bytes() == features_path(out / "seed-0" / "results.json").read_bytes()
    assert block["seeds"] == [0, 1] and block["results"] == ["seed-0/results.json", "seed-1/results.json"]
    ok = [n for n, m in seeds[0]["metrics"].items() if all(d["metrics"][n]["status"] == "ok" for d in seeds)]
    assert ok and list(block["metrics"]) == ok
    for name, m in block["metrics"].items():
        values = [d["metrics"][name]["value"] for d in seeds]  # what each seed's results file says
        assert m["values"] == values
        assert m["mean"] == pytest.approx(np.mean(values), rel=1e-15)
        assert m["sd"] == pytest.approx(np.std(values, ddof=1), abs=1e-15)
        assert (m["min"], m["max"]) == (min(values), max(values))
    # 3. the summary says the spread, a line per metric
    assert "seeds 0, 1 of mean-frame" in text and f"results: {out / 'results.json'}" in text
    assert all(any(ln.split()[:1] == [n] and " sd " in ln for ln in text.splitlines()) for n in ok), text
    # 4. read like any results file; compare of two such files tests the seeds; the board files it
    read_results(out / "results.json")
    _, cmp, _ = run_cli("compare", str(out / "results.json"), str(out / "results.json"), "--json")
    cmp = json.loads(cmp)
    assert cmp["seeds"]["a"] == [0, 1] and cmp["metrics"]["psnr"]["seeds"]["verdict"] == "within the seed spread"
    lb = tmp_path / "lb"
    lb.mkdir()
    run_cli("leaderboard", "add", str(out / "results.json"), "--root", str(lb), "--name", "mf-seeds")
    assert json.loads((lb / "results" / "mf-seeds.json").read_text())["seeds"]["metrics"] == block["metrics"]
    # 5. the same command again resumes every seed and rewrites the same block
    run_cli(*args)
    assert json.loads((out / "results.json").read_text())["seeds"] == block


def test_seeds_run_refusals(synthtown_smoke, tmp_path):
    """Before any work, in one line: fewer than 2 seeds, an --out holding a single run, a seed
    folder holding another run, a results.json of something else."""
    base = ["reproduce", "--method", "mean-frame", "--data", str(synthtown_smoke), "--quiet"]

    def refused(out, *extra, why):
        rc, _, err = run_cli(*base, "--out", str(out), *extra, check=2)
        assert err.count("\n") == 1 and why in err and "Traceback" not in err, err
        assert not (out / "seed-0" / "submission").exists()  # no seed ran

    refused(tmp_path / "one", "--seeds", "1", why="--seeds 1: expected 2 or more seeds")
    single = tmp_path / "single"
    single.mkdir()
    (single / "config.json").write_text(json.dumps({"method": "mean-frame", "seed": 0}))
    refused(single, "--seeds", "2", why="holds a single run (its config.json)")
    other = tmp_path / "other"
    (other / "seed-4").mkdir(parents=True)
    (other / "seed-4" / "config.json").write_text(json.dumps({"method": "mvs", "method_version": "1", "seed": 4}))
    refused(other, "--seeds", "2", "--seed", "3", why="method 'mvs' there, 'mean-frame' here")
    scored = tmp_path / "scored"
    scored.mkdir()
    (scored / "results.json").write_text(json.dumps({"format": "skyeyes-bench/results@1"}))
    refused(scored, "--seeds", "2", why="already exists; pass --force")
