"""Issue 57: runs of several seeds (`reproduce --seeds N`). The `seeds` block's spread, `compare`'s
seed test on synthetic results with a known answer, both ways: Welch's t on the seeds' headline
values against scipy's `ttest_ind(equal_var=False).confidence_interval()` where A and B ran other
seeds, the paired t against `ttest_rel(...).confidence_interval()` where they ran the same ones;
the block's checks when a file is read, and the API returning what the command prints."""

import json
import math

import numpy as np
import pytest
from builders.evaluation import blurred_submission, make_dataset, protocol_env
from conftest import run_cli
from scipy import stats as sps

import skyeyes_bench as sb
from skyeyes_bench.data.layout import open_dataset
from skyeyes_bench.seeds import EXCEEDS, WITHIN, seed_test, spread

#: Per-seed values with a known answer. "far": the seed means differ by 2 dB against sds of 0.1
#: (Welch's interval ~ [1.75, 2.25]); "near": by 0.1 against sds of 0.4-0.5 (interval ~ [-1.1, 1.3]);
#: A three seeds, B three ("far") or four ("near").
FAR = {"psnr": ([20.0, 20.1, 19.9], [18.0, 18.1, 17.9]), "fid": ([50.0, 51.0, 49.0], [60.0, 61.5, 58.5])}
NEAR = {"psnr": ([20.0, 20.5, 19.5], [19.9, 20.4, 19.4, 19.9]), "fid": ([50.0, 53.0, 47.0], [51.0, 54.0, 48.0, 51.0])}
#: The same seeds in A and B, each seed moving both runs alike (a shared stage): "steady", A better
#: by 0.2 dB (FID 1) in every seed give or take 0.05 (0.2) against a spread of 2 dB (10) between
#: seeds, which the paired test sees (interval ~ [0.08, 0.32]) and Welch's does not; "mixed", the
#: per-seed advantages change sign.
STEADY = {"psnr": ([20.0, 22.0, 18.0], [19.8, 21.75, 17.85]), "fid": ([50.0, 60.0, 40.0], [51.0, 61.2, 40.8])}
MIXED = {"psnr": ([20.0, 22.0, 18.0], [19.7, 22.2, 17.9]), "fid": ([50.0, 60.0, 40.0], [51.0, 59.0, 40.5])}


def _block(values: dict, seeds: list[int]) -> dict:
    """A `seeds` block written by hand (numpy's mean and ddof=1 sd), not by the module tested."""
    return {"seeds": seeds, "results": [f"seed-{s}/results.json" for s in seeds],
            "metrics": {m: {"values": list(v), "mean": float(np.mean(v)), "sd": float(np.std(v, ddof=1)),
                            "min": min(v), "max": max(v)} for m, v in values.items()}}


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """Two results files of the same frames (evaltest@1, 2 scenes x 2 sequences: too few clusters
    for intervals, so no sampling: the seed test is what is checked), and a folder to write
    copies of them with `seeds` blocks into."""
    tmp = tmp_path_factory.mktemp("seeds")
    with protocol_env(tmp) as mp:
        root = make_dataset(tmp / "ds", scenes=2)
        ds = open_dataset(root)
        for k, s in (("a", 0.7), ("b", 1.5)):
            sb.evaluate(blurred_submission(ds, tmp / k, sigma=s, method=k), root, out=tmp / f"{k}.json",
                        allow_missing=True)
        yield tmp, mp


def _files(world, tmp_path, a_block: dict | None, b_block: dict | None):
    """Copies of A's and B's results in tmp_path with the given `seeds` blocks (None: none)."""
    tmp, _ = world
    paths = []
    for k, blk in (("a", a_block), ("b", b_block)):
        doc = json.loads((tmp / f"{k}.json").read_text())
        if blk is not None:
            doc["seeds"] = blk
        (tmp_path / f"{k}.json").write_text(json.dumps(doc))
        paths.append(tmp_path / f"{k}.json")
    return paths


def _scipy_interval(va, vb, metric: str) -> tuple[float, float]:
    """Welch's 95% interval of the advantage of A (A - B, or B - A where lower is better) by scipy."""
    if metric == "fid":  # lower is better: the advantage is B - A
        va, vb = vb, va
    ci = sps.ttest_ind(va, vb, equal_var=False).confidence_interval(0.95)
    return float(ci.low), float(ci.high)


def test_spread_is_numpys_mean_and_sample_sd():
    got = spread([1.0, 2.0, 4.0])
    assert got["mean"] == pytest.approx(np.mean([1, 2, 4]), rel=1e-15)
    assert got["sd"] == pytest.approx(np.std([1, 2, 4], ddof=1), rel=1e-15)
    assert (got["min"], got["max"], got["values"]) == (1.0, 4.0, [1.0, 2.0, 4.0])
    # an exact seed (PSNR +inf): no spread, the mean is the infinity
    assert spread([math.inf, 30.0]) == {"values": [math.inf, 30.0], "mean": math.inf, "sd": None, "min": 30.0,
                                        "max": math.inf}


@pytest.mark.parametrize("metric", ["psnr", "fid"])
@pytest.mark.parametrize("case, verdict", [(FAR, EXCEEDS), (NEAR, WITHIN)])
def test_seed_test_against_scipy(metric, case, verdict):
    va, vb = case[metric]
    got = seed_test(va, vb, metric, 0.95)
    lo, hi = _scipy_interval(va, vb, metric)
    assert got["interval"] == pytest.approx([lo, hi], rel=1e-9, abs=1e-12)
    assert got["verdict"] == verdict
    sign = 1 if metric == "psnr" else -1
    assert got["advantage"] == pytest.approx(sign * (np.mean(va) - np.mean(vb)), rel=1e-12)
    assert got["se"] == pytest.approx(math.sqrt(np.var(va, ddof=1) / len(va) + np.var(vb, ddof=1) / len(vb)))
    # the closed form: d +- t_{0.975, df} se, df by Welch-Satterthwaite
    sa, sb_ = np.var(va, ddof=1) / len(va), np.var(vb, ddof=1) / len(vb)
    df = (sa + sb_) ** 2 / (sa ** 2 / (len(va) - 1) + sb_ ** 2 / (len(vb) - 1))
    assert got["df"] == pytest.approx(df, rel=1e-12)
    half = sps.t.ppf(0.975, df) * math.sqrt(sa + sb_)
    assert got["interval"] == pytest.approx([got["advantage"] - half, got["advantage"] + half], rel=1e-12)


def _scipy_paired_interval(va, vb, metric: str) -> tuple[float, float]:
    """The paired t's 95% interval of the advantage of A by scipy."""
    if metric == "fid":
        va, vb = vb, va
    ci = sps.ttest_rel(va, vb).confidence_interval(0.95)
    return float(ci.low), float(ci.high)


@pytest.mark.parametrize("metric", ["psnr", "fid"])
@pytest.mark.parametrize("case, paired, welch", [(STEADY, EXCEEDS, WITHIN), (MIXED, WITHIN, WITHIN)])
def test_paired_seed_test_against_scipy(metric, case, paired, welch):
    va, vb = case[metric]
    got = seed_test(va, vb, metric, 0.95, paired=True)
    assert got["test"] == "paired" and got["df"] == len(va) - 1
    assert got["interval"] == pytest.approx(list(_scipy_paired_interval(va, vb, metric)), rel=1e-9, abs=1e-12)
    sign = 1 if metric == "psnr" else -1
    d = sign * (np.array(va) - np.array(vb))
    assert got["differences"] == pytest.approx(d.tolist(), rel=1e-12)
    assert got["advantage"] == pytest.approx(d.mean(), rel=1e-12)
    assert got["se"] == pytest.approx(np.std(d, ddof=1) / math.sqrt(len(d)), rel=1e-12)
    assert got["verdict"] == paired
    # the same values unpaired: Welch's, whose spread between seeds hides a steady advantage
    assert seed_test(va, vb, metric, 0.95)["verdict"] == welch


def test_seed_test_without_spread():
    """Deterministic methods (mean-frame): sd 0 in both; the difference is exact."""
    assert seed_test([1.0, 1.0], [1.0, 1.0], "psnr", 0.95)["verdict"] == WITHIN
    got = seed_test([2.0, 2.0], [1.0, 1.0], "psnr", 0.95)
    assert (got["verdict"], got["interval"], got["df"]) == (EXCEEDS, [1.0, 1.0], None)
    assert seed_test([math.inf, 30.0], [20.0, 21.0], "psnr", 0.95)["status"] == "skipped"
    # paired: every seed's difference the same, however far apart the seeds
    got = seed_test([20.0, 25.0], [19.0, 24.0], "psnr", 0.95, paired=True)
    assert (got["verdict"], got["interval"], got["df"]) == (EXCEEDS, [1.0, 1.0], None)


@pytest.mark.parametrize("case, verdict", [(FAR, EXCEEDS), (NEAR, WITHIN)])
def test_compare_of_two_seed_runs(world, tmp_path, case, verdict):
    """Both ways: A better by far more than the seeds' spread exceeds it, by less does not; B
    against A flips the advantage and its interval; the API returns what `compare --json` prints."""
    vals = {m: v for m, v in case.items()}
    a, b = _files(world, tmp_path, _block({m: v[0] for m, v in vals.items()}, [0, 1, 2]),
                  _block({m: v[1] for m, v in vals.items()}, list(range(10, 10 + len(vals["psnr"][1])))))
    _, out, _ = run_cli("compare", str(a), str(b), "--json")
    res = json.loads(out)
    assert res == sb.compare(a, b)  # the API: the same seed block
    assert res["seeds"]["a"] == [0, 1, 2] and res["seeds"]["level"] == 0.95 and "note" not in res["seeds"]
    for metric, (va, vb) in vals.items():
        t = res["metrics"][metric]["seeds"]
        assert t["verdict"] == verdict and t["status"] == "ok"
        assert t["interval"] == pytest.approx(list(_scipy_interval(va, vb, metric)), rel=1e-9)
        assert t["advantage"] > 0  # A is the better one in every case
    # the other way round: B against A
    back = sb.compare(b, a)
    for metric, (va, vb) in vals.items():
        t, u = res["metrics"][metric]["seeds"], back["metrics"][metric]["seeds"]
        assert u["advantage"] == pytest.approx(-t["advantage"]) and u["verdict"] == t["verdict"]
        assert u["interval"] == pytest.approx([-t["interval"][1], -t["interval"][0]])
    # metrics scored in the seeds' runs but not in every seed: said, not tested
    assert res["metrics"]["ssim"]["seeds"] == {"status": "skipped", "note": "ssim not scored in every seed of A"}
    # the summary: one line per metric under it
    _, text, _ = run_cli("compare", str(a), str(b))
    lines = text.splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.lstrip().startswith("psnr "))
    assert lines[i + 1].lstrip().startswith("seeds: A ") and lines[i + 1].endswith(verdict), lines[i + 1]
    assert "95% Welch [" in lines[i + 1]
    assert "seeds: A 3 seeds (0, 1, 2), B " in text


@pytest.mark.parametrize("case, verdict", [(STEADY, EXCEEDS), (MIXED, WITHIN)])
def test_compare_of_runs_of_the_same_seeds_is_paired(world, tmp_path, case, verdict):
    """A and B of the same seeds: each metric's test is the paired t (scipy's interval), which
    finds a steady advantage that the spread between seeds hides from Welch's, and finds none
    where the per-seed advantages change sign; renumbering B's seeds makes it Welch's again."""
    a, b = _files(world, tmp_path, _block({m: v[0] for m, v in case.items()}, [0, 1, 2]),
                  _block({m: v[1] for m, v in case.items()}, [0, 1, 2]))
    res = sb.compare(a, b)
    assert "paired" in res["seeds"]["test"]
    for metric, (va, vb) in case.items():
        t = res["metrics"][metric]["seeds"]
        assert t["test"] == "paired" and t["verdict"] == verdict
        assert t["interval"] == pytest.approx(list(_scipy_paired_interval(va, vb, metric)), rel=1e-9)
    _, text, _ = run_cli("compare", str(a), str(b))
    lines = text.splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.lstrip().startswith("psnr "))
    assert "95% paired t [" in lines[i + 1] and lines[i + 1].endswith(verdict), lines[i + 1]
    assert "paired t (the same seeds)" in text
    a, b = _files(world, tmp_path, _block({m: v[0] for m, v in case.items()}, [0, 1, 2]),
                  _block({m: v[1] for m, v in case.items()}, [3, 4, 5]))
    res = sb.compare(a, b)
    for metric, (va, vb) in case.items():
        t = res["metrics"][metric]["seeds"]
        assert t["test"] == "welch" and t["verdict"] == WITHIN
        assert t["interval"] == pytest.approx(list(_scipy_interval(va, vb, metric)), rel=1e-9)


def test_compare_when_one_or_neither_ran_seeds(world, tmp_path):
    blk = _block({m: v[0] for m, v in FAR.items()}, [0, 1, 2])
    a, b = _files(world, tmp_path, None, blk)
    res = sb.compare(a, b)
    assert res["seeds"]["note"] == f"only B ({b}) ran several seeds (3); A is one run: no seed test"
    assert all("seeds" not in m for m in res["metrics"].values())
    _, text, _ = run_cli("compare", str(a), str(b))
    assert sum("seeds" in ln for ln in text.splitlines()) == 1 and f"only B ({b}) ran several seeds" in text
    a, b = _files(world, tmp_path, None, None)  # neither: nothing changes
    res = sb.compare(a, b)
    assert "seeds" not in res and all("seeds" not in m for m in res["metrics"].values())
    assert "seeds" not in run_cli("compare", str(a), str(b))[1]


@pytest.mark.parametrize("edit, field, why", [
    (lambda s: s.update(seeds=[0]) or s.update(results=s["results"][:1]) or
     [m.update(values=m["values"][:1]) for m in s["metrics"].values()], "seeds.seeds", "2 or more seeds"),
    (lambda s: s.update(seeds=[0, 0, 1]), "seeds.seeds", "distinct seeds"),
    (lambda s: s["metrics"]["psnr"].update(values=[1.0, 2.0]), "seeds.metrics.psnr.values", "3 values"),
    (lambda s: s["results"].__setitem__(1, "../elsewhere.json"), "seeds.results[1]", "relative path"),
    (lambda s: s["metrics"]["psnr"]["values"].__setitem__(0, math.nan), "seeds.metrics.psnr.values[0]", "NaN"),
    (lambda s: s["metrics"]["fid"].update(sd="wide"), "seeds.metrics.fid.sd", "a number"),
    (lambda s: s.update(results="seed-0"), "seeds.results", "a list"),
])
def test_a_bad_seeds_block_is_one_line(world, tmp_path, edit, field, why):
    blk = _block({m: v[0] for m, v in FAR.items()}, [0, 1, 2])
    edit(blk)
    a, b = _files(world, tmp_path, blk, None)
    rc, out, err = run_cli("compare", str(a), str(b), check=2)
    assert err.count("\n") == 1 and "Traceback" not in err and str(a) in err and f"'{field}'" in err and why in err, err


def _seed_copy(world, folder, key: str, seed: int, psnr_shift: float = 0.0, hardware: dict | None = None):
    """results `key` (a or b) as folder/seed-<seed>/results.json with its sidecar; PSNR's headline
    value moved by `psnr_shift` (a seed that trained differently); `hardware`: the run's machine."""
    import shutil

    tmp, _ = world
    d = folder / f"seed-{seed}"
    d.mkdir(parents=True)
    doc = json.loads((tmp / f"{key}.json").read_text())
    doc["metrics"]["psnr"]["value"] += psnr_shift
    if hardware is not None:
        doc["submission"]["hardware"] = hardware
    (d / "results.json").write_text(json.dumps(doc))
    shutil.copyfile(tmp / doc["features"]["file"], d / doc["features"]["file"])
    return doc


def test_seeds_command_combines_seeds_run_apart(world, tmp_path):
    """`skyeyes-bench seeds DIR`: the lowest seed's results intact with the block of every seed
    folder there (numpy's mean and sd of what each file says), its sidecar beside it."""
    docs = {s: _seed_copy(world, tmp_path / "row", "a", s, shift) for s, shift in ((2, 0.0), (0, 1.0), (5, -0.5))}
    code, text, _ = run_cli("seeds", str(tmp_path / "row"))
    assert code == 0 and "wrote" in text and "seeds 0, 2, 5 of a" in text
    top = json.loads((tmp_path / "row" / "results.json").read_text())
    block = top.pop("seeds")
    sidecar, want = top.pop("features"), dict(docs[0])
    assert sidecar["sha256"] == want.pop("features")["sha256"]  # the same features, named after the new file
    assert top == want and block["seeds"] == [0, 2, 5] and "hardware" not in block  # one machine: nothing to say
    assert block["results"] == ["seed-0/results.json", "seed-2/results.json", "seed-5/results.json"]
    values = [docs[s]["metrics"]["psnr"]["value"] for s in (0, 2, 5)]
    got = block["metrics"]["psnr"]
    assert got["values"] == values and got["mean"] == pytest.approx(np.mean(values), rel=1e-12)
    assert got["sd"] == pytest.approx(np.std(values, ddof=1), rel=1e-12)
    assert (tmp_path / "row" / sidecar["file"]).is_file()
    _, again, _ = run_cli("compare", str(tmp_path / "row" / "results.json"), str(tmp_path / "row" / "results.json"),
                          "--json")
    assert json.loads(again)["seeds"]["a"] == [0, 2, 5]
    assert run_cli("seeds", str(tmp_path / "row"))[0] == 0  # its own earlier file is replaced


def test_seeds_run_on_different_machines_are_said(world, tmp_path):
    """Seeds from two machines (CPU runs and a GPU's): the block names each seed's machine and the
    summary says the spread includes the drift between them; a bad `hardware` field is one line."""
    cpu = {"cpu": "AMD EPYC", "cores": 2, "gpu": None}
    for s, hw in ((0, cpu), (1, cpu), (3, {"cpu": "Intel Xeon", "cores": 16, "gpu": "NVIDIA H200"})):
        _seed_copy(world, tmp_path / "row", "a", s, hardware=hw)
    code, text, _ = run_cli("seeds", str(tmp_path / "row"))
    block = json.loads((tmp_path / "row" / "results.json").read_text())["seeds"]
    gpu = "Intel Xeon (16 cores), NVIDIA H200"  # as the board's Hardware column writes it
    assert code == 0 and block["hardware"] == ["AMD EPYC (2 cores)", "AMD EPYC (2 cores)", gpu]
    assert f"seed 3 on {gpu}" in text and "different machines" in text, text
    blk = _block({m: v[0] for m, v in FAR.items()}, [0, 1, 2])
    blk["hardware"] = ["AMD EPYC (2 cores)", "NVIDIA H200"]  # one machine short
    (tmp_path / "bad").mkdir()
    a, b = _files(world, tmp_path / "bad", blk, None)
    _, _, err = run_cli("compare", str(a), str(b), check=2)
    assert err.count("\n") == 1 and "'seeds.hardware'" in err and "expected 3 machines" in err, err


@pytest.mark.parametrize("layout, why", [
    ("one", "1 seed-<s>/results.json found, expected 2 or more"),
    ("other-method", "field 'submission.method' is 'b', expected 'a'"),
    ("single-run", "holds a single run"),
])
def test_seeds_command_refuses_in_one_line(world, tmp_path, layout, why):
    row = tmp_path / "row"
    _seed_copy(world, row, "a", 0)
    if layout == "other-method":
        _seed_copy(world, row, "b", 1)
    if layout == "single-run":
        _seed_copy(world, row, "a", 1)
        (row / "config.json").write_text("{}")
    code, _, err = run_cli("seeds", str(row), check=2)
    assert code == 2 and why in err and len(err.strip().splitlines()) == 1, err
    assert not (row / "results.json").exists()
