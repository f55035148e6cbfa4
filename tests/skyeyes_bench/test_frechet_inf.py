"""FID∞ / FVD∞ (skyeyes_bench.frechet_inf; Chong & Forsyth, CVPR 2020).

Against an independent computation (the subset / fit loop written out with numpy, scipy's sqrtm
and np.polyfit), and in a simulation with Gaussian features whose Fréchet distance is known in
closed form: FD of N samples is biased upward by more than its interval at small N, FD∞ is not
and its interval covers the truth; the same checks reject the plain FD put in FD∞'s place."""

import math

import numpy as np
import pytest
import scipy.linalg
from builders.evaluation import TEST_PROTOCOL, blurred_submission, make_dataset, protocol_env
from builders.frechet_sim import fd_bias_of, gaussians, simulate

from skyeyes_bench import comparison, estimators, stats
from skyeyes_bench.frechet_inf import FrechetInfinity, extrapolate, subset_sizes
from skyeyes_bench.metricspec import METRICS
from skyeyes_bench.protocol import MetricSpec

# --------------------------------------------------------------------------- the loop, written out


def _fd_sqrtm(x, y):
    """Fréchet distance of the sample statistics of x [n, D] and y [n, D], as pytorch-fid computes it."""
    s1, s2 = np.cov(x, rowvar=False), np.cov(y, rowvar=False)
    covmean = scipy.linalg.sqrtm(s1 @ s2).real
    return float(((x.mean(0) - y.mean(0)) ** 2).sum() + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean))


def _fd_inf_loop(x, y, num_sizes, min_fraction, num_subsets, seed):
    """Chong & Forsyth's recipe on paired rows, plainly: sizes evenly spaced from min_fraction n to n,
    `num_subsets` random subsets of each (the same rows of x and y), the mean FD per size, a
    least-squares line against 1 / size, its intercept."""
    n = len(x)
    lo = max(2, round(min_fraction * n))
    sizes = sorted({int(v) for v in np.rint(np.linspace(lo, n, num_sizes))})
    rng = np.random.default_rng(seed)
    values = []
    for size in sizes:
        fds = []
        for _ in range(num_subsets):
            rows = rng.permutation(n)[:size]
            fds.append(_fd_sqrtm(x[rows], y[rows]))
        values.append(np.mean(fds))
    slope, intercept = np.polyfit(1.0 / np.array(sizes), values, 1)
    return intercept, sizes, values


def _features(n, d, seed):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(d, d)) / np.sqrt(d)
    x = rng.normal(size=(n, d)) @ a.T
    y = 0.3 + rng.normal(size=(n, d)) * 0.8
    return x, y


def test_subset_sizes_and_fit():
    assert subset_sizes(2048, 15, 0.5).tolist() == sorted({int(round(1024 + 1024 * k / 14)) for k in range(15)})
    s = subset_sizes(10, 15, 0.5)
    assert s.tolist() == [5, 6, 7, 8, 9, 10]  # duplicates dropped; the last is every row
    assert subset_sizes(3, 15, 0.1).tolist() == [2, 3] and len(subset_sizes(1)) == 0
    # a line in 1 / N is recovered exactly; otherwise the least-squares intercept np.polyfit gives
    sizes = np.array([100, 150, 200, 400])
    assert extrapolate(sizes, 7.0 + 300.0 / sizes) == pytest.approx(7.0, rel=1e-12)
    values = np.array([3.0, 2.1, 2.2, 1.5])
    assert extrapolate(sizes, values) == pytest.approx(np.polyfit(1.0 / sizes, values, 1)[1], rel=1e-12)
    assert math.isnan(extrapolate(np.array([5]), np.array([1.0])))


@pytest.mark.filterwarnings("ignore::scipy.linalg.LinAlgWarning")  # sqrtm of a singular product (gram route)
@pytest.mark.parametrize("n, d", [(60, 12), (20, 24)], ids=["covariance route", "gram route"])
def test_matches_the_loop_written_out(n, d):
    x, y = _features(n, d, seed=n)
    want, sizes, _ = _fd_inf_loop(x, y, num_sizes=9, min_fraction=0.3, num_subsets=3, seed=7)
    spec = MetricSpec(name="fid_inf", num_sizes=9, min_fraction=0.3, num_subsets=3)
    got = estimators.frechet_inf(x, y, spec, 7)
    rel = 1e-7 if n > d else 1e-6  # sqrtm of a singular product (fewer rows than dimensions) is less accurate
    assert got == pytest.approx(want, rel=rel)
    fi = FrechetInfinity.from_features(x, y, np.zeros(n, np.int64), 1, spec, 7)
    curve_sizes, curve = fi.curve(np.ones(n))
    assert curve_sizes.tolist() == sizes and curve[-1] == pytest.approx(_fd_sqrtm(x, y), rel=1e-6)
    # a half-sample (weights 0 / 1) is the loop on its rows; a weight of 2 repeats a row
    w = (np.arange(n) % 2).astype(np.float64)
    assert fi(w, w) == pytest.approx(_fd_inf_loop(x[w > 0], y[w > 0], 9, 0.3, 3, 7)[0], rel=rel)
    w[:4] = 2
    rows = np.repeat(np.arange(n), w.astype(int))
    assert fi(w, w) == pytest.approx(_fd_inf_loop(x[rows], y[rows], 9, 0.3, 3, 7)[0], rel=rel)


def test_edge_cases():
    x, y = _features(40, 8, seed=1)
    fi = FrechetInfinity(x, y, seed=3)
    w = np.ones(40)
    assert FrechetInfinity(x, x)(w, w) == pytest.approx(0.0, abs=1e-9)  # identical sets: 0 at every size
    assert fi(w, w) == fi(w, w) and fi(w, w) != FrechetInfinity(x, y, seed=4)(w, w)  # the seed, only the seed
    with pytest.raises(ValueError, match="paired"):
        fi(w, np.r_[0.0, w[1:]])
    assert math.isnan(fi(np.r_[1.0, 1.0, np.zeros(38)], np.r_[1.0, 1.0, np.zeros(38)]))  # 2 rows: no line
    assert METRICS["fid_inf"].min_rows == METRICS["fvd_inf"].min_rows == 3  # so results say `unavailable` there
    assert not math.isnan(fi(np.r_[1.0, 1.0, 1.0, np.zeros(37)], np.r_[1.0, 1.0, 1.0, np.zeros(37)]))
    # the defaults are Chong & Forsyth's 15 sizes and 1 subset each, from N / 2
    fi = FrechetInfinity.from_features(x, y, np.zeros(40, np.int64), 1)
    assert (fi.num_sizes, fi.min_fraction, fi.num_subsets, fi.seed) == (15, 0.5, 1, 0)


# --------------------------------------------------------------------------- simulation


def _verdict(draws: dict, truth: float, fd_bias: dict, cover_all: float, cover_each: float) -> list[str]:
    """Why estimates of the truth fail (empty: they pass). draws: N -> [(value, lo, hi)] over
    repeated data sets; fd_bias: N -> the plain FD's mean bias in the same draws. At every N the
    mean must lie within 3 standard errors of the truth or within half the plain FD's bias of it;
    the intervals must cover the truth in at least `cover_all` of all draws and `cover_each` of
    each N's."""
    why = []
    for n, rows in draws.items():
        v = np.array([r[0] for r in rows])
        bias, se = v.mean() - truth, v.std(ddof=1) / math.sqrt(len(v))
        if abs(bias) > 3 * se and abs(bias) > 0.5 * fd_bias[n]:
            why.append(f"N={n}: bias {bias:.3f} (standard error {se:.3f}, plain FD's {fd_bias[n]:.3f})")
        each = np.mean([lo <= truth <= hi for _, lo, hi in rows])
        if each < cover_each:
            why.append(f"N={n}: coverage {each:.2f}")
    cover = np.mean([lo <= truth <= hi for rows in draws.values() for _, lo, hi in rows])
    if cover < cover_all:
        why.append(f"coverage {cover:.2f}")
    return why


def test_gaussian_simulation_fd_biased_fd_inf_not():
    """8 draws per N (`_simulate`). FD at small N is biased by more than its interval; FD∞ is not,
    and its intervals cover the truth in at least 90% of the draws (75% at each N). The slow
    tier's test repeats this at the stated level over 256 draws."""
    draws, truth = simulate(8, seed=1)
    fd_bias = fd_bias_of(draws, truth)
    fd64 = np.array(draws["fid"][64])
    # FD at N = 64: above the truth in every draw, on average by more than its interval's half-width
    # (half-sampling shifts the interval down by the bias's 1 / N part, so the interval itself still
    # reaches the truth: what is biased is the value)
    assert (fd64[:, 0] > truth).all()
    assert fd_bias[64] > ((fd64[:, 2] - fd64[:, 1]) / 2).mean() > 0
    assert _verdict(draws["fid_inf"], truth, fd_bias, 0.90, 0.75) == []
    # ... and the same checks fail for the plain FD in FD∞'s place: they can fail
    assert any(w.startswith("N=64: bias") for w in _verdict(draws["fid"], truth, fd_bias, 0.90, 0.75))


@pytest.mark.slow
def test_gaussian_simulation_fd_inf_covers_at_the_stated_level():
    """Issue 39's done-when: over 2 x 32 draws at each N (256 in all), FD∞'s 95% intervals cover
    the truth in at least 95% of all draws and 87.5% of each N's (at most 4 misses of 32), and its
    mean is unbiased at every N. Measured (docs/metrics.md): 0.99 pooled about the centre. The
    intervals reflected about the value itself (before the centre) covered 0.93 and 0.89 on these
    seeds, which this bar fails: checked here on the same replicates, so the bar can fail."""
    pooled = {"fid": {}, "fid_inf": {}, "fid_inf_value": {}}
    for seed in (1, 2):
        draws, truth = simulate(32, seed)
        for name in pooled:
            for n, rows in draws[name].items():
                pooled[name].setdefault(n, []).extend(rows)
    fd_bias = fd_bias_of(pooled, truth)
    assert _verdict(pooled["fid_inf"], truth, fd_bias, 0.95, 0.875) == []
    # the same replicates reflected about the value: below the level, so this bar can fail
    assert any(w.startswith("coverage") for w in _verdict(pooled["fid_inf_value"], truth, fd_bias, 0.95, 0.875))


# --------------------------------------------------------------------------- end to end

INF_PROTOCOL = TEST_PROTOCOL.replace('id = "evaltest"', 'id = "evalinf"').replace("[statistics]", """
[metrics.fid_inf]
extractor = "random-image-64"
resize = "none"
num_sizes = 15
min_fraction = 0.5
num_subsets = 1

[metrics.fvd_inf]
extractor = "random-video-64"
resize = "none"
clip_length = 4
clip_stride = 4
num_sizes = 15
min_fraction = 0.5
num_subsets = 4

[statistics]""")


@pytest.fixture(scope="module")
def inf_scored(tmp_path_factory):
    from skyeyes_bench.data.layout import open_dataset
    from skyeyes_bench.evaluate import evaluate
    from skyeyes_bench.submission import write_template

    tmp = tmp_path_factory.mktemp("inf")
    with protocol_env(tmp, INF_PROTOCOL):
        data = make_dataset(tmp / "ds", protocol="evalinf@1", scenes=3)
        ds = open_dataset(data)
        subs = {"gt": write_template(ds, tmp / "gt", from_ground_truth=True),
                "b1": blurred_submission(ds, tmp / "b1", sigma=0.7),
                "b2": blurred_submission(ds, tmp / "b2", sigma=1.5)}
        res = {k: evaluate(v, data=data, out=tmp / f"{k}.json", progress=False) for k, v in subs.items()}
        yield res, tmp


def test_evaluate_reports_fid_inf_from_the_fid_features(inf_scored):
    from skyeyes_bench.evaluate import read_results
    from skyeyes_bench.protocol import load_protocol

    res, tmp = inf_scored
    with protocol_env(tmp, INF_PROTOCOL):
        protocol = load_protocol("evalinf@1")
        doc, feats = read_results(tmp / "b2.json", features=True)
    assert list(doc["metrics"]) == ["psnr", "ssim", "lpips", "fid", "kid", "fvd", "kvd", "fid_inf", "fvd_inf"]
    assert set(feats) == {"random-image-64", "random-video-64"}  # no extractor of their own
    for name, ex, unit, n in (("fid_inf", "random-image-64", "frame", 96), ("fvd_inf", "random-video-64", "clip", 24)):
        m = doc["metrics"][name]
        assert m["status"] == "ok" and (m["extractor"], m["unit"], m["n"]) == (ex, unit, n)
        f = feats[ex]
        assert m["value"] == estimators.frechet_inf(f["sub"], f["gt"], protocol.metric(name), 0)
        assert m["interval"][0] <= m["value"] <= m["interval"][1] and len(m["replicates"]) == 200
        # the interval's centre: FD∞ averaged over the seeds 0..15, each computed on its own here
        seeds = [estimators.frechet_inf(f["sub"], f["gt"], protocol.metric(name), s) for s in range(16)]
        assert m["interval_centre"] == pytest.approx(np.mean(seeds), rel=1e-12) != m["value"]
        # ... and the interval: percentiles of centre - (replicate - centre) at half-sampling's scale
        # (K = 6 sequences: sqrt(3 / 3) = 1), widened to hold the value, clipped at 0; the stored
        # replicates are rounded to 6 digits
        d = 2 * m["interval_centre"] - np.array(m["replicates"], np.float64)
        lo, hi = np.quantile(d, [0.025, 0.975], method="inverted_cdf")
        want = [max(min(lo, m["value"]), min(0.0, m["value"])), max(hi, m["value"])]
        assert m["interval"] == pytest.approx(want, rel=1e-5, abs=1e-9)
        plain = doc["metrics"][name[:3]]["value"]
        assert 0 < m["value"] < plain  # the extrapolation removes an upward bias
    assert res["gt"]["metrics"]["fid_inf"]["value"] == pytest.approx(0.0, abs=1e-9)


def test_compare_recomputes_the_same_replicates_from_features(inf_scored):
    from skyeyes_bench.evaluate import read_results

    res, tmp = inf_scored
    with protocol_env(tmp, INF_PROTOCOL):
        (a, fa), (b, fb) = (read_results(tmp / f"{k}.json", features=True) for k in ("b1", "b2"))
        stored = comparison.compare_results(a, b, emcee_steps=60)
        for doc in (a, b):  # without stored replicates compare resamples the features with the protocol's settings
            for name in ("fid_inf", "fvd_inf"):
                doc["metrics"][name]["replicates"] = None
        again = comparison.compare_results(a, b, fa, fb, emcee_steps=60)
    for name in ("fid_inf", "fvd_inf"):
        want = stored["metrics"][name]["bootstrap_interval"]
        assert stored["metrics"][name]["status"] == "ok" and want
        assert again["metrics"][name]["bootstrap_interval"] == pytest.approx(want, rel=1e-4)
        # both about the advantage of the two centres (lower is better: B's centre - A's)
        centre = b["metrics"][name]["interval_centre"] - a["metrics"][name]["interval_centre"]
        assert stored["metrics"][name]["interval_centre"] == pytest.approx(centre, rel=1e-12)
        assert again["metrics"][name]["interval_centre"] == pytest.approx(centre, rel=1e-9)
        for doc in (a, b):  # a file scored before the centre, with no sidecar: about the values, as before
            doc["metrics"][name].pop("interval_centre")
    with protocol_env(tmp, INF_PROTOCOL):
        old = comparison.compare_results(a, b, emcee_steps=60)
    for name in ("fid_inf", "fvd_inf"):
        assert "interval_centre" not in old["metrics"][name]


def test_compare_says_when_sample_counts_differ(inf_scored):
    """Issue 39: one line naming each set metric's counts when A and B differ; in the refusal when
    the protocols differ, as a warning otherwise; nothing when they agree."""
    import copy

    from skyeyes_bench.errors import UserError

    res, tmp = inf_scored
    with protocol_env(tmp, INF_PROTOCOL):
        a, b = res["b1"], res["b2"]
        assert "warnings" not in comparison.compare_results(a, b, emcee_steps=60)
        b2 = copy.deepcopy(b)
        b2["metrics"]["fvd_inf"]["n"] = 48  # as if scored on twice the clips
        out = comparison.compare_results(a, b2, emcee_steps=60, names=("a.json", "b.json"))
        (w,) = out["warnings"]
        assert "FVD∞ 24 clips (a.json), 48 clips (b.json)" in w and "FID " not in w and "1/N" in w
        b2["protocol"]["ref"] = "evalinf@2"
        with pytest.raises(UserError, match=r"different protocols.*FVD∞ 24 clips \(a.json\), 48 clips \(b.json\)"):
            comparison.compare_results(a, b2, emcee_steps=60, names=("a.json", "b.json"))
