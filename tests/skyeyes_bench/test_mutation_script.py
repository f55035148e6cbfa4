"""bench/mutation.py's sampling and its interval (the campaign itself is hours of CPU: not a test)."""

from __future__ import annotations

import json

import pytest
from builders.bench_scripts import load_bench
from scipy.stats import beta


@pytest.fixture(scope="module")
def mutation():
    return load_bench("mutation")


def test_sample_is_a_seeded_subset_per_module_independent_of_listing_order(mutation):
    names = {"a.py": [f"a.x__mutmut_{i}" for i in range(50)], "b": ["b.y__mutmut_1", "b.y__mutmut_2"]}
    s = mutation.sample_mutants(names, 10, seed=3)
    assert len(s["a.py"]) == 10 and len(set(s["a.py"])) == 10 and set(s["a.py"]) <= set(names["a.py"])
    assert sorted(s["b"]) == sorted(names["b"])  # fewer than n: all of them
    shuffled = {"a.py": names["a.py"][::-1], "b": names["b"][::-1]}
    assert mutation.sample_mutants(shuffled, 10, seed=3) == s
    assert mutation.sample_mutants(names, 10, seed=4)["a.py"] != s["a.py"]
    # the draw is uniform: over many seeds every name is picked about n/len of the time
    hits = {k: 0 for k in names["a.py"]}
    for seed in range(400):
        for k in mutation.sample_mutants({"a.py": names["a.py"]}, 10, seed)["a.py"]:
            hits[k] += 1
    assert min(hits.values()) > 40 and max(hits.values()) < 125  # expected 80 each (binomial sd ~8)


@pytest.mark.parametrize("killed,checked", [(0, 20), (17, 20), (20, 20), (244, 300)])
def test_rate_interval_is_clopper_pearson(mutation, killed, checked):
    lo, hi = mutation.rate_interval(killed, checked)
    # closed form: the 2.5% and 97.5% quantiles of Beta(k, n-k+1) and Beta(k+1, n-k), 0 / 1 at the ends
    want_lo = beta.ppf(0.025, killed, checked - killed + 1) if killed else 0.0
    want_hi = beta.ppf(0.975, killed + 1, checked - killed) if killed < checked else 1.0
    assert lo == pytest.approx(want_lo, abs=1e-9) and hi == pytest.approx(want_hi, abs=1e-9)
    assert lo <= killed / checked <= hi


def test_collect_counts_only_the_sample(mutation, tmp_path):
    pytest.importorskip("mutmut")
    meta = tmp_path / "mutants" / "pkg" / "m.py.meta"
    meta.parent.mkdir(parents=True)
    # mutmut's exit codes: 1 killed, 0 survived, 33 no tests, 36 timeout, None not checked
    codes = {"pkg.m.f__mutmut_1": 1, "pkg.m.f__mutmut_2": 0, "pkg.m.f__mutmut_3": 33,
             "pkg.m.f__mutmut_4": 36, "pkg.m.f__mutmut_5": None}
    meta.write_text(json.dumps({"exit_code_by_key": codes}))
    (tmp_path / "mutants" / "other.py.meta").write_text(json.dumps({"exit_code_by_key": {"other.g__mutmut_1": 0}}))
    every = mutation.collect(tmp_path, ["pkg"])["pkg"]
    assert (every["killed"], every["survived"], every["no tests"], every["timeout"], every["not checked"]) == (1, 1, 1, 1, 1)
    only = {"pkg": ["pkg.m.f__mutmut_1", "pkg.m.f__mutmut_3"]}
    part = mutation.collect(tmp_path, ["pkg"], only)["pkg"]
    assert sum(part.values()) == 2 and (part["killed"], part["no tests"]) == (1, 1)
    assert mutation.survivors(tmp_path, ["pkg"], only) == ["pkg.m.f__mutmut_3"]
    assert sorted(mutation.survivors(tmp_path, ["pkg"])) == ["pkg.m.f__mutmut_2", "pkg.m.f__mutmut_3"]
    rows = mutation.report({"pkg": part}, {"pkg": 5})
    assert rows[0]["checked"] == 2 and rows[0]["kill_rate"] == 0.5 and rows[0]["population"] == 5
    assert rows[0]["interval_95"] == pytest.approx(mutation.rate_interval(1, 2))
