"""skyeyes_bench.metricspec: the one metric table, and the modules that read it.

The table is plain data (no numpy on import); every protocol shipped names only metrics from it;
every entry point it names resolves; the set-metric estimators and bootstraps it names agree
with independent computations."""

import subprocess
import sys
import tomllib

import numpy as np
import pytest
from conftest import ROOT

from skyeyes_bench import comparison, leaderboard, paths, protocol, stats
from skyeyes_bench.errors import UserError
from skyeyes_bench.metricspec import FRAME_METRICS, METRICS, SEQUENCE_METRICS, SET_METRICS, SETTINGS, metric_def
from skyeyes_bench.registry import load_entry_point


def test_spec_module_imports_no_numpy():
    code = ("import sys, skyeyes_bench.metricspec, skyeyes_bench.protocol; "
            "print(sorted(m for m in ('numpy', 'scipy', 'torch') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "[]"


def test_shipped_protocols_name_only_table_metrics():
    files = sorted(paths.builtin_protocols_dir().glob("*/v[0-9]*.toml"))  # not val.toml: a split, no metrics
    assert files, "no shipped protocols found"
    for f in files:
        names = set(tomllib.loads(f.read_text())["metrics"])
        assert names <= set(METRICS), f"{f}: metrics {sorted(names - set(METRICS))} not in metricspec.METRICS"
    for p in protocol.list_protocols(paths.builtin_protocols_dir()):
        assert set(p.metric_names) <= set(METRICS)


def test_table_is_complete_and_consistent():
    regions = ("psnr_seen", "psnr_unseen", "ssim_seen", "ssim_unseen", "lpips_seen", "lpips_unseen", "unseen_share")
    assert tuple(METRICS) == ("psnr", "ssim", "lpips", "fid", "fid_inf", "kid", "fvd", "fvd_inf", "kvd", *regions,
                              "warp", "warp_floor")
    assert FRAME_METRICS == ("psnr", "ssim", "lpips", *regions, "warp", "warp_floor")
    assert SET_METRICS == ("fid", "fid_inf", "kid", "fvd", "fvd_inf", "kvd")
    assert SEQUENCE_METRICS == (*regions, "warp", "warp_floor")
    for name, m in METRICS.items():
        assert m.name == name and m.kind in ("frame", "set")
        assert m.keys <= set(SETTINGS), f"{name}: keys {sorted(m.keys - set(SETTINGS))} have no metricspec.Setting"
        assert not m.settings  # the built-in metrics share their keys' settings
        assert all(m.setting(k) is SETTINGS[k] for k in m.keys)
        assert m.extractor == ("extractor" in m.keys)
        assert bool(m.depth) == ("depth_tolerance" in m.keys) == bool(m.per_sequence)
        assert m.pool in ("mean", "mse") and (m.pool == "mse") == (m.weighted and name.startswith("psnr"))
        if m.kind == "frame":
            assert bool(m.per_frame) != bool(m.per_sequence)  # frame by frame, or a sequence at a time
            assert m.features is None and m.estimator is None and m.bootstrap is None
            assert callable(load_entry_point(m.per_frame or m.per_sequence))
        else:
            assert m.features in ("image", "clip") and m.extractor and m.per_frame is None
            assert callable(load_entry_point(m.estimator)) and callable(load_entry_point(m.bootstrap))
            assert ("clip_length" in m.keys) == (m.features == "clip")
    # the readers derive from the table, not from copies of it
    assert protocol.MetricSpec("kid", subset_size=10).as_dict() == {"subset_size": 10}
    with pytest.raises(UserError, match="metric 'psnr': unknown setting 'window' \\(known: aggregate\\)"):
        protocol.MetricSpec("psnr", window=3)
    assert stats.LOWER_IS_BETTER == {"lpips", "fid", "fid_inf", "kid", "fvd", "fvd_inf", "kvd", "lpips_seen",
                                     "lpips_unseen", "unseen_share", "warp", "warp_floor"}
    assert {n for n, m in METRICS.items() if m.reference} == {"unseen_share", "warp_floor"}
    assert [stats.higher_is_better(n) for n in METRICS] == [m.higher_is_better for m in METRICS.values()]
    assert leaderboard.METRIC_ORDER == tuple(METRICS)
    assert leaderboard.LABEL["kid"] == "KID" and leaderboard._DIGITS["kid"] == 4


def test_unknown_metric_lists_the_known_ones():
    with pytest.raises(Exception, match="unknown metric 'xyz'; known: fid, .*kvd"):
        metric_def("xyz")


def test_set_metric_bootstrap_follows_the_table():
    from skyeyes_bench.frechet_inf import FrechetInfinity

    rng = np.random.default_rng(0)
    k = 4
    seq = np.repeat(np.arange(k), 5)
    x, y = rng.normal(size=(20, 8)), rng.normal(size=(20, 8)) + 0.3
    w = np.ones(k)
    for name in SET_METRICS:
        fn = stats.set_metric_bootstrap(name, x, y, seq, k)
        kind = {"fid": stats.FrechetBootstrap, "fvd": stats.FrechetBootstrap, "fid_inf": FrechetInfinity,
                "fvd_inf": FrechetInfinity}.get(name, stats.MMDBootstrap)
        assert type(fn) is kind
        # all sequences drawn once: the bootstrap equals the point estimate on the full sets
        full = stats.set_metric_samples(fn, seq, seq, w[None, :])[0]
        settings = protocol.MetricSpec(name=name)  # no subsets: the full-sample MMD^2
        want = load_entry_point(metric_def(name).estimator)(x, y, settings, 0)
        assert full == pytest.approx(want, rel=1e-9, abs=1e-12)


def test_estimators_match_direct_computations():
    from skyeyes_bench.metrics import frechet_distance, kernel_mmd

    rng = np.random.default_rng(1)
    x, y = rng.normal(size=(30, 6)), rng.normal(size=(25, 6))
    fid = load_entry_point(METRICS["fid"].estimator)(x, y, protocol.MetricSpec(name="fid"), 0)
    want = frechet_distance(x.mean(0), np.cov(x, rowvar=False), y.mean(0), np.cov(y, rowvar=False))
    assert fid == pytest.approx(want, rel=1e-10)
    kid_spec = protocol.MetricSpec(name="kid", subset_size=10, num_subsets=3)
    kid = load_entry_point(METRICS["kid"].estimator)(x, y, kid_spec, 7)
    assert kid == kernel_mmd(x, y, subset_size=10, num_subsets=3, seed=7)


def test_paired_bootstrap_is_the_one_compare_uses():
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=9), rng.normal(size=9)
    kw = dict(resamples=200, level=0.9, seed=5)
    out = comparison.compare_per_sequence(a, b, "ssim", walkers=8, steps=60, burn=20, **kw)
    assert out["bootstrap_interval"] == list(stats.advantage_interval(stats.advantage(a, b, "ssim"), **kw))
    # +inf and -inf advantages drawn together make a resampled mean undefined: no interval
    assert stats.advantage_interval(np.array([np.inf, -np.inf, 1.0]), **kw) is None


def test_builtin_protocol_ids_ignore_the_protocols_override(tmp_path, monkeypatch):
    from skyeyes_bench.evaluate import builtin_protocol_ids

    monkeypatch.setenv("SKYEYES_PROTOCOLS", str(tmp_path))
    assert paths.protocols_dir() == tmp_path
    assert builtin_protocol_ids() == set(protocol.available(paths.builtin_protocols_dir()))
    assert "synthtown" in builtin_protocol_ids()
