"""skyeyes_bench.stats: clustered bootstrap, set-metric resampling, Bayesian comparison.

Each fast path is checked against a slow, independent computation (materialised resamples,
scipy's sqrtm, explicit U-statistics)."""

import math

import numpy as np
import pytest
import scipy.linalg
import scipy.stats

from skyeyes_bench import bayes, comparison, stats


def _slow_fid(x, y):
    mu1, mu2 = x.mean(0), y.mean(0)
    s1, s2 = np.cov(x, rowvar=False), np.cov(y, rowvar=False)
    covmean = scipy.linalg.sqrtm(s1 @ s2).real
    return float(((mu1 - mu2) ** 2).sum() + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean))


def _slow_mmd(x, y):
    d = x.shape[1]
    k = lambda a, b: (a @ b.T / d + 1.0) ** 3  # noqa: E731
    kxx, kyy, kxy = k(x, x), k(y, y), k(x, y)
    n, m = len(x), len(y)
    return float((kxx.sum() - np.trace(kxx)) / (n * (n - 1)) + (kyy.sum() - np.trace(kyy)) / (m * (m - 1))
                 - 2 * kxy.mean())


def test_frame_metric_samples_match_materialised_resamples():
    rng = np.random.default_rng(1)
    k = 5
    clusters = np.repeat(np.arange(k), [3, 4, 2, 5, 1])
    values = rng.normal(size=len(clusters))
    idx = stats.resample_indices(k, 50, seed=3)
    got = stats.frame_metric_samples(values, clusters, stats.resample_counts(idx, k))
    want = [np.concatenate([values[clusters == s] for s in row]).mean() for row in idx]
    np.testing.assert_allclose(got, want, rtol=1e-12)


def test_frame_metric_samples_propagate_inf_only_when_drawn():
    clusters = np.array([0, 0, 1, 1])
    values = np.array([30.0, np.inf, 20.0, 22.0])
    counts = np.array([[2.0, 0.0], [0.0, 2.0], [1.0, 1.0]])
    got = stats.frame_metric_samples(values, clusters, counts)
    assert got[0] == np.inf and got[2] == np.inf
    assert got[1] == pytest.approx(21.0)
    lo, hi = stats.percentile_interval(np.array([1.0, 2.0, np.inf, np.inf]), 0.5)
    assert (lo, hi) == (1.0, np.inf)


def test_sequence_psnr_from_mean_mse():
    clusters = np.array([0, 0, 1, 1])
    psnr = np.array([20.0, 30.0, np.inf, np.inf])
    got = stats.sequence_psnr(psnr, clusters, 2)
    assert got[0] == pytest.approx(-10 * math.log10((0.01 + 0.001) / 2))
    assert got[1] == np.inf


@pytest.mark.parametrize("n, d", [(12, 40), (60, 6)])  # Gram route (N <= D) and covariance route
def test_frechet_bootstrap_matches_sqrtm_on_materialised_resample(n, d):
    rng = np.random.default_rng(0)
    x = rng.normal(size=(n, d))
    y = rng.normal(loc=0.3, size=(n, d)) * 1.5
    fb = stats.FrechetBootstrap(x, y)
    w = rng.integers(0, 3, size=n).astype(float)
    w[:3] = 1
    got = fb(w, w)
    xr, yr = np.repeat(x, w.astype(int), axis=0), np.repeat(y, w.astype(int), axis=0)
    assert got == pytest.approx(_slow_fid(xr, yr), rel=1e-6, abs=1e-8)
    assert fb(np.ones(n), np.ones(n)) == pytest.approx(_slow_fid(x, y), rel=1e-6)
    assert stats.FrechetBootstrap(x, x)(w, w) == pytest.approx(0.0, abs=1e-6)


def test_mmd_bootstrap_matches_explicit_u_statistic():
    rng = np.random.default_rng(2)
    x, y = rng.normal(size=(15, 8)), rng.normal(0.5, size=(15, 8))
    clusters = np.array([0, 0, 1, 1, 1, 2, 3, 3, 3, 3, 4, 4, 2, 0, 1])  # not contiguous on purpose
    mb = stats.MMDBootstrap(x, y, clusters, clusters, 5)
    mb._CHUNK = 4  # exercise the streaming
    mb.__init__(x, y, clusters, clusters, 5)
    assert mb(np.ones(5), np.ones(5)) == pytest.approx(_slow_mmd(x, y), rel=1e-10)
    c = np.array([2.0, 0.0, 1.0, 3.0, 1.0])
    w = c[clusters].astype(int)
    xr, yr = np.repeat(x, w, axis=0), np.repeat(y, w, axis=0)
    assert mb(c, c) == pytest.approx(_slow_mmd(xr, yr), rel=1e-10)


@pytest.mark.parametrize("n, d, gram", [(12, 40, True), (40, 40, True), (41, 40, False), (60, 6, False)])
def test_frechet_bootstrap_route_follows_shape(n, d, gram):
    """Frame space (N x N Gram matrices) exactly when no set has more frames than dimensions:
    the covariance route at N << D is a D x D eigenproblem per resample (2048^2 for Inception)."""
    rng = np.random.default_rng(4)
    fb = stats.FrechetBootstrap(rng.normal(size=(n, d)), rng.normal(size=(max(n - 3, 1), d)))
    assert fb.gram is gram and hasattr(fb, "g12") is gram


@pytest.mark.filterwarnings("ignore::scipy.linalg.LinAlgWarning")  # singular rank-1 covariances
@pytest.mark.parametrize("d", [3, 30])  # covariance and Gram routes
def test_frechet_bootstrap_at_two_samples_and_below(d):
    """Two rows a side is the smallest defined sample (covariance with n - 1 = 1); one is NaN."""
    rng = np.random.default_rng(5)
    x, y = rng.normal(size=(4, d)), rng.normal(1.0, size=(4, d))
    fb = stats.FrechetBootstrap(x, y)
    w2 = np.array([1.0, 1.0, 0.0, 0.0])
    want = _slow_fid(x[:2], y[:2])  # rank-1 covariances: sqrtm is exact here
    assert np.isfinite(want) and fb(w2, w2) == pytest.approx(want, rel=1e-6)
    assert fb(np.array([2.0, 0, 0, 0]), w2) == pytest.approx(_slow_fid(x[[0, 0]], y[:2]), rel=1e-6, abs=1e-9)
    one = np.array([0.0, 1.0, 0.0, 0.0])
    assert math.isnan(fb(one, w2)) and math.isnan(fb(w2, one))


def test_mmd_bootstrap_at_two_samples_and_below():
    """The U-statistic needs two rows a side: exact at two, NaN at one, on either side."""
    rng = np.random.default_rng(6)
    x, y = rng.normal(size=(3, 5)), rng.normal(0.5, size=(3, 5))
    cl = np.array([0, 1, 2])
    mb = stats.MMDBootstrap(x, y, cl, cl, 3)
    two, one = np.array([1.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
    assert mb(two, two) == pytest.approx(_slow_mmd(x[:2], y[:2]), rel=1e-10)
    assert mb(two, np.array([0.0, 2.0, 0.0])) == pytest.approx(_slow_mmd(x[:2], y[[1, 1]]), rel=1e-10)
    assert math.isnan(mb(one, two)) and math.isnan(mb(two, one))


def test_hdi_of_normal_samples():
    s = np.random.default_rng(0).normal(size=200_000)
    lo, hi = bayes.hdi(s, 0.95)
    assert lo == pytest.approx(-1.96, abs=0.03) and hi == pytest.approx(1.96, abs=0.03)


_FAST = dict(resamples=500, level=0.95, seed=0, walkers=16, steps=1000, burn=200)


def test_compare_identical_methods_zero_variance():
    a = np.array([25.0, 27.0, 30.0, 26.0, 28.0, 24.0])
    out = comparison.compare_per_sequence(a, a.copy(), "psnr", **_FAST)
    assert out["advantage_mean"] == 0.0
    assert out["bootstrap_interval"] == [0.0, 0.0]
    b = out["bayes"]
    assert b["p_a_better"] == 0.5 and b["hdi"] == [0.0, 0.0] and "zero variance" in b["note"]
    assert not b["fitted"]


@pytest.mark.parametrize("k", [1, 4])
def test_compare_too_few_clusters(k):
    """Below 5 clusters: the point estimate stays, interval and P(better) are 'too few'."""
    a, b = np.full(k, 0.3), np.linspace(0.4, 0.6, k)
    out = comparison.compare_per_sequence(a, b, "lpips", unit="scene", **_FAST)
    assert out["advantage_mean"] == pytest.approx(np.mean(b - a))  # lower LPIPS is better: A better
    assert out["bootstrap_interval"] is None and out["interval_note"] == f"too few scenes (K={k})"
    assert out["bayes"]["p_a_better"] is None and out["bayes"]["note"] == f"too few scenes (K={k})"


def test_compare_clear_difference_and_sign_convention():
    rng = np.random.default_rng(5)
    b = rng.normal(0.5, 0.05, size=20)
    a = b - 0.1 + rng.normal(0, 0.01, size=20)  # A has lower LPIPS: better
    out = comparison.compare_per_sequence(a, b, "lpips", **_FAST)
    assert out["bayes"]["fitted"]
    assert out["bayes"]["p_a_better"] > 0.99
    lo, hi = out["bayes"]["hdi"]
    d = b - a  # independent reference: the classical t interval of the mean difference
    half = scipy.stats.t.ppf(0.975, len(d) - 1) * d.std(ddof=1) / math.sqrt(len(d))
    assert lo == pytest.approx(d.mean() - half, abs=0.3 * half)
    assert hi == pytest.approx(d.mean() + half, abs=0.3 * half)
    assert 0.2 < out["bayes"]["acceptance"] < 0.8
    out2 = comparison.compare_per_sequence(b, a, "lpips", **_FAST)
    assert out2["bayes"]["p_a_better"] < 0.01


def test_compare_heavy_outlier_is_robust():
    rng = np.random.default_rng(7)
    d = rng.normal(0.5, 0.1, size=20)
    d[0] = 50.0  # one broken sequence
    out = comparison.compare_per_sequence(d, np.zeros(20), "psnr", **_FAST)
    assert out["advantage_mean"] == pytest.approx(d.mean())  # ~3: dragged by the outlier
    lo, hi = out["bayes"]["hdi"]
    assert lo < 0.5 < hi and hi < 1.0  # the Student-t posterior is not
    assert out["bayes"]["nu_median"] < 10  # heavy tails inferred


def test_compare_psnr_inf():
    a = np.array([np.inf, np.inf, 30.0, 31.0, 32.0])
    b = np.array([np.inf, 28.0, 29.0, 30.0, 31.0])
    out = comparison.compare_per_sequence(a, b, "psnr", **_FAST)
    assert out["bootstrap_interval"][1] == np.inf
    assert not out["bayes"]["fitted"] and "infinite" in out["bayes"]["note"]
    assert out["bayes"]["p_a_better"] is None  # one tie (0), one +inf, one +1: not all > 0
    d = stats.advantage(a, b, "psnr")
    np.testing.assert_array_equal(d, [0.0, np.inf, 1.0, 1.0, 1.0])


# --------------------------------------------------------------------------- clusters, half-sampling


def test_cluster_map_groups_sequences_by_scene():
    ids = ["test-0-lane01/yaw000", "test-0-lane01/yaw045", "test-0-lane00/yaw000", "b/x", "test-0-lane00/yaw045"]
    idx, names = stats.cluster_map(ids, "scene")
    want_names = []
    for s in ids:  # slow reference: first-seen order of the part before the last '/'
        if s.split("/")[0] not in want_names:
            want_names.append(s.split("/")[0])
    assert names == want_names == ["test-0-lane01", "test-0-lane00", "b"]
    assert [names[i] for i in idx] == [s.split("/")[0] for s in ids]
    idx, names = stats.cluster_map(ids, "sequence")
    assert names == ids and list(idx) == list(range(5))
    assert stats.too_few(4, "scene") == "too few scenes (K=4)" and stats.too_few(5, "scene") is None


def test_replicate_counts_depend_only_on_seed_resamples_and_k():
    a = stats.replicate_counts(9, 300, seed=4)
    assert (a.sum(axis=1) == 4).all() and set(np.unique(a)) == {0.0, 1.0}
    np.testing.assert_array_equal(a, stats.replicate_counts(9, 300, seed=4))
    assert not np.array_equal(a, stats.replicate_counts(9, 300, seed=5))
    # every cluster is drawn about equally often (4/9 of the rows)
    assert np.abs(a.mean(axis=0) - 4 / 9).max() < 0.1


@pytest.mark.parametrize("k", [6, 9])
def test_half_sampling_draws_have_the_variance_of_the_mean(k):
    """For a mean of K cluster values, the draws est - s (theta_m - est) have variance S^2 / K
    (S^2 the sample variance, ddof=1): the delete-d jackknife identity, here by Monte Carlo."""
    v = np.random.default_rng(k).normal(size=k) ** 2
    reps = stats.frame_metric_samples(v, np.arange(k), stats.replicate_counts(k, 40_000, seed=0))
    draws = stats.replicate_draws(float(v.mean()), reps, k)
    assert draws.var() == pytest.approx(v.var(ddof=1) / k, rel=0.05)
    assert draws.mean() == pytest.approx(v.mean(), abs=0.02 * v.std())


def test_set_metric_interval_contains_its_estimate_where_percentile_does_not():
    """Few frames per scene, high-dimensional features: duplicated frames inflate FID under the
    bootstrap with replacement, so its percentile interval lies above the estimate; the
    reported (half-sampling) interval contains it."""
    rng = np.random.default_rng(3)
    k, per, d = 8, 2, 64
    x, y = rng.normal(size=(k * per, d)), rng.normal(0.2, size=(k * per, d))
    cl = np.repeat(np.arange(k), per)
    fb = stats.FrechetBootstrap(x, y)
    est = _slow_fid(x, y)
    boot = stats.set_metric_samples(fb, cl, cl, stats.resample_counts(stats.resample_indices(k, 300, 0), k))
    lo, hi = stats.percentile_interval(boot[np.isfinite(boot)], 0.95)
    assert not lo <= est <= hi and lo > est  # the old interval excludes its own estimate
    reps = stats.set_metric_samples(fb, cl, cl, stats.replicate_counts(k, 300, 0))
    lo2, hi2, widened = stats.interval_from_replicates(est, reps, 0.95, k)
    assert lo2 <= est <= hi2 and lo2 < hi2
    # each replicate is FID on the chosen scenes only (slow reference)
    c = stats.replicate_counts(k, 300, 0)[7].astype(bool)
    assert reps[7] == pytest.approx(_slow_fid(x[c[cl]], y[c[cl]]), rel=1e-6)


def test_interval_from_replicates_not_widened_when_the_estimate_is_an_end():
    """Every replicate equal to the estimate: the interval is the point, and it was not widened."""
    assert stats.interval_from_replicates(2.0, [2.0, 2.0, 2.0], 0.95, 6) == (2.0, 2.0, False)


@pytest.mark.filterwarnings("ignore::scipy.linalg.LinAlgWarning")
def test_frechet_eigh_on_rank_deficient_covariances():
    """3 samples in 12 dimensions: the covariances are singular and eigh returns eigenvalues a
    rounding below 0; they count as 0 (no NaN from their square roots)."""
    rng = np.random.default_rng(7)
    x, y = rng.normal(size=(3, 12)), rng.normal(0.5, size=(5, 12))
    s1, s2 = np.cov(x, rowvar=False), np.cov(y, rowvar=False)
    assert np.linalg.eigvalsh(s1).min() < 0  # the case this test is about
    got = stats.frechet_eigh(x.mean(0), s1, y.mean(0), s2)
    assert np.isfinite(got) and got == pytest.approx(_slow_fid(x, y), rel=1e-6)


def test_interval_from_replicates_by_hand():
    est, reps, k = 2.0, np.array([2.5, 1.5, 3.0, None, 2.0]), 6
    s = np.sqrt(3 / 3)
    draws = sorted(est - s * (np.array([2.5, 1.5, 3.0, 2.0]) - est))
    assert stats.interval_from_replicates(est, reps, 0.5, k)[:2] == (draws[0], draws[2])
    assert stats.interval_from_replicates(est, [None, None], 0.95, k) is None
    # all draws on one side: widened to the estimate, and said so
    lo, hi, widened = stats.interval_from_replicates(1.0, [0.2, 0.3, 0.4], 0.95, 6)
    assert widened and lo == 1.0 and hi == pytest.approx(1.8)  # draws 1.6..1.8 lie above 1.0
    assert stats.round_replicates(np.array([1.23456789, np.nan, -np.inf, 12345678.9])) == [1.23457, None, -np.inf,
                                                                                         12345700.0]


def test_paired_replicates_self_zero_and_known_shift():
    """Replicates of two results on the same clusters use the same rows: differencing A with
    itself gives exact zeros, a per-frame shift of 0.1 gives 0.1 in every replicate."""
    rng = np.random.default_rng(0)
    cl = np.repeat(np.arange(7), 3)
    v = rng.random(len(cl))
    counts = stats.replicate_counts(7, 200, 0)
    ra = stats.frame_metric_samples(v, cl, counts)
    rb = stats.frame_metric_samples(v, cl, stats.replicate_counts(7, 200, 0))
    np.testing.assert_array_equal(stats.advantage(ra, rb, "ssim"), 0.0)
    rs = stats.frame_metric_samples(v + 0.1, cl, counts)
    np.testing.assert_allclose(stats.advantage(rs, ra, "ssim"), 0.1, rtol=1e-12)
    lo, hi, _ = stats.interval_from_replicates(0.1, stats.advantage(rs, ra, "ssim"), 0.95, 7)
    assert lo == pytest.approx(0.1) and hi == pytest.approx(0.1)


def test_set_metric_samples_computes_a_repeated_resample_once():
    """Half-sampling 6 clusters has C(6, 3) = 20 distinct draws: 300 replicates call the metric
    20 times, and each replicate equals the metric called directly on its own weights."""
    import itertools

    k = 6
    cl = np.repeat(np.arange(k), 2)  # 2 rows per cluster
    calls = []

    def fn(w1, w2):
        calls.append(1)
        return float(w1 @ np.arange(len(w1)) + 0.5 * w2.sum())

    counts = stats.replicate_counts(k, 300, 0)
    reps = stats.set_metric_samples(fn, cl, cl, counts)
    distinct = {tuple(c) for c in counts}
    assert len(calls) == len(distinct) <= len(list(itertools.combinations(range(k), k // 2)))
    calls.clear()
    assert np.array_equal(reps, [fn(c[cl], c[cl]) for c in counts])


@pytest.mark.parametrize("kind", ["fid", "kid"])
@pytest.mark.parametrize("draws", ["half-sampling", "bootstrap"])
def test_set_metric_samples_resample_submission_and_ground_truth_together(kind, draws):
    """Each replicate is the set metric on the SAME clusters' rows of both sets (a paired
    resample), materialised and computed from scratch (scipy sqrtm / explicit U-statistic).
    The two sets differ by cluster, so resampling only one side gives other numbers."""
    rng = np.random.default_rng(11)
    k, d = 6, 5
    cl = np.array([0, 0, 1, 1, 1, 2, 2, 3, 3, 3, 4, 4, 5, 5, 5, 0])  # uneven, not contiguous
    x = rng.normal(size=(len(cl), d)) + cl[:, None] * 0.4  # cluster-dependent shift, both sides
    y = rng.normal(size=(len(cl), d)) * 1.3 + cl[:, None] * 0.4 + 0.2
    counts = (stats.replicate_counts(k, 25, 0) if draws == "half-sampling"
              else stats.resample_counts(stats.resample_indices(k, 25, 4), k))
    fn = stats.set_metric_bootstrap(kind, x, y, cl, k)
    got = stats.set_metric_samples(fn, cl, cl, counts)
    slow = _slow_fid if kind == "fid" else _slow_mmd
    for r, c in enumerate(counts):
        reps = c[cl].astype(int)  # how often each row is drawn
        want = slow(np.repeat(x, reps, axis=0), np.repeat(y, reps, axis=0))
        assert got[r] == pytest.approx(want, rel=1e-6, abs=1e-9), r


# --------------------------------------------------------------------------- gaps found by bench/mutation.py


def test_polynomial_kernel_defaults_are_kid_closed_form():
    """KID's kernel (Binkowski et al. 2018): k(x, y) = (x.y / D + 1)^3 with the defaults."""
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(4, 7)), rng.normal(size=(3, 7))
    want = [[(float(a @ b) / 7 + 1.0) ** 3 for b in y] for a in x]
    np.testing.assert_allclose(stats.polynomial_kernel(x, y), want, rtol=1e-12)
    np.testing.assert_allclose(stats.polynomial_kernel(x, y, degree=2, gamma=0.5, coef0=0.0),
                               [[(0.5 * float(a @ b)) ** 2 for b in y] for a in x], rtol=1e-12)


def test_resample_indices_draw_every_cluster_uniformly():
    k, r = 5, 4000
    idx = stats.resample_indices(k, r, seed=1)
    assert idx.shape == (r, k) and idx.min() == 0 and idx.max() == k - 1
    freq = np.bincount(idx.ravel(), minlength=k)
    assert scipy.stats.chisquare(freq).pvalue > 1e-3, freq
    np.testing.assert_array_equal(idx, stats.resample_indices(k, r, seed=1))
    assert not np.array_equal(idx, stats.resample_indices(k, r, seed=2))


def test_frame_metric_samples_with_negative_infinities_and_an_empty_cluster():
    """Materialised means (numpy): -inf where a drawn cluster holds -inf, NaN with +inf and -inf
    together; a cluster with no frame (the last) contributes nothing."""
    k = 5
    clusters = np.array([0, 0, 1, 2, 2, 3])  # cluster 4 has no frame
    values = np.array([1.0, 2.0, -np.inf, 4.0, np.inf, 6.0])
    counts = np.array([[1, 0, 0, 1, 3], [0, 1, 0, 1, 0], [1, 1, 1, 0, 0], [0, 0, 0, 2, 1], [1, 0, 0, 0, 0]], float)
    got = stats.frame_metric_samples(values, clusters, counts)
    for r, c in enumerate(counts):
        rows = np.repeat(values, c[clusters].astype(int))
        with np.errstate(invalid="ignore"):
            want = np.mean(rows)
        assert (np.isnan(got[r]) and np.isnan(want)) or got[r] == want, (r, got[r], want)
    with np.errstate(invalid="ignore"):  # 0 / 0 for the empty sequence: NaN, said by numpy
        seq = stats.sequence_psnr(np.array([20.0, 30.0, 25.0]), np.array([0, 0, 1]), 3)  # sequence 2: no frame
    assert seq.shape == (3,) and seq[1] == pytest.approx(25.0) and np.isnan(seq[2])


@pytest.mark.parametrize("kind", ["fid", "kid"])
def test_set_metric_bootstrap_with_a_cluster_without_rows_and_too_few_rows(kind):
    """A sequence shorter than a clip has no clip rows: its cluster is empty (here the last).
    Fewer than 2 rows on either side has no value (NaN)."""
    rng = np.random.default_rng(3)
    k, d = 4, 5
    cl = np.array([0, 0, 1, 1, 1, 2, 2, 0])  # cluster 3: no row
    x, y = rng.normal(size=(8, d)), rng.normal(0.3, size=(8, d))
    fn = stats.set_metric_bootstrap(kind, x, y, cl, k)
    slow = _slow_fid if kind == "fid" else _slow_mmd
    counts = np.array([[1.0, 1.0, 0.0, 1.0], [0.0, 1.0, 1.0, 1.0], [1.0, 0.0, 1.0, 0.0]])
    got = stats.set_metric_samples(fn, cl, cl, counts)
    for r, c in enumerate(counts):
        rows = c[cl] > 0
        assert got[r] == pytest.approx(slow(x[rows], y[rows]), rel=1e-6, abs=1e-9), r
    one = np.array([0.0, 0.0, 0.0, 1.0]) if kind == "kid" else np.array([0.0, 0.0, 0.0, 1.0])[cl]
    assert np.isnan(fn(one, one))
    single = np.zeros(len(cl))
    single[2] = 1.0
    if kind == "fid":
        assert np.isnan(fn(single, np.ones(len(cl)))) and np.isnan(fn(np.ones(len(cl)), single))


def test_bayes_summary_without_a_fit_says_why():
    """The documented outcomes without sampling: too few clusters, a missing value, infinite
    differences (P = 1 / 0 when all on one side, else none), zero variance at a non-zero value."""
    kw = dict(unit="scene", walkers=8, steps=50, burn=10, seed=0)
    few = comparison.bayes_summary(np.ones(3), **kw)
    assert few == {"fitted": False, "estimand": comparison.BAYES_ESTIMAND.format(unit="scene"), "clusters": 3,
                   "note": "too few scenes (K=3)", "p_a_better": None, "hdi": None}
    nan = comparison.bayes_summary(np.array([1.0, np.nan, 2.0, 3.0, 4.0]), **kw)
    assert nan["note"] == "a scene has no value for one method" and nan["p_a_better"] is None and nan["hdi"] is None
    d = np.array([0.5, np.inf, 0.2, 0.1, 0.3])
    up = comparison.bayes_summary(d, **kw)
    assert up["p_a_better"] == 1.0 and up["hdi"] is None and "1 scene(s) have an infinite difference" in up["note"]
    assert comparison.bayes_summary(-d, **kw)["p_a_better"] == 0.0
    assert comparison.bayes_summary(np.array([0.5, -np.inf, 0.2, 0.1, 0.3]), **kw)["p_a_better"] is None
    flat = comparison.bayes_summary(np.full(6, -0.25), **kw)
    assert not flat["fitted"] and flat["mu_mean"] == -0.25 and flat["hdi"] == [-0.25, -0.25]
    assert flat["p_a_better"] == 0.0 and comparison.bayes_summary(np.full(6, 0.25), **kw)["p_a_better"] == 1.0


def test_compare_per_sequence_reports_its_inputs():
    a, b = np.array([0.30, 0.32, 0.35, 0.31, 0.29, 0.33]), np.array([0.40, 0.41, 0.39, 0.45, 0.38, 0.42])
    out = comparison.compare_per_sequence(a, b, "lpips", unit="scene", **_FAST)
    assert {k: out[k] for k in ("metric", "higher_is_better", "clusters", "level")} == {
        "metric": "lpips", "higher_is_better": False, "clusters": 6, "level": 0.95}
    assert out["advantage_mean"] == pytest.approx(np.mean(b - a))
    lo, hi = out["bootstrap_interval"]
    assert lo <= out["advantage_mean"] <= hi and lo > 0
    assert out["bayes"]["fitted"] and out["bayes"]["clusters"] == 6 and "per-scene" in out["bayes"]["estimand"]
    nan = comparison.compare_per_sequence(a, np.where(np.arange(6) == 2, np.nan, b), "lpips", **_FAST)
    assert math.isnan(nan["advantage_mean"]) and nan["bootstrap_interval"] is None


def _neighbours(sorted_samples: np.ndarray, value: float) -> tuple[float, float]:
    """The order statistics one place beyond those bracketing `value`: where an interval end
    computed by another quantile convention (interpolating, not inverted cdf) may fall."""
    i = int(np.searchsorted(sorted_samples, value))
    return sorted_samples[max(i - 2, 0)], sorted_samples[min(i + 1, len(sorted_samples) - 1)]


@pytest.mark.parametrize("level", [0.8, 0.9, 0.95])
def test_bca_and_basic_intervals_match_scipy_on_the_same_bootstrap_distribution(level):
    """bench/coverage.py's alternatives to half-sampling, against scipy.stats.bootstrap fed our
    replicates (`bootstrap_result`, no new resamples): scipy computes BCa's bias correction and
    its jackknife acceleration itself, from the data (Efron & Tibshirani 1993, 14.3)."""
    rng = np.random.default_rng(3)
    x = rng.exponential(size=15)  # skewed: z0 and the acceleration are both far from 0
    boots = x[stats.resample_indices(len(x), 20000, seed=1)].mean(axis=1)
    jackknife = np.array([np.delete(x, i).mean() for i in range(len(x))])
    s = np.sort(boots)
    bca = stats.bca_interval(x.mean(), boots, jackknife, level)

    class Previous:
        bootstrap_distribution = boots

    for method, ours in [("BCa", bca), ("basic", stats.basic_interval(x.mean(), boots, level))]:
        ref = scipy.stats.bootstrap((x,), np.mean, n_resamples=0, bootstrap_result=Previous, method=method,
                                    confidence_level=level).confidence_interval
        for got, want in zip(ours, (ref.low, ref.high)):
            if method == "basic":  # reflected: compare the order statistics it came from
                got, want = 2 * x.mean() - got, 2 * x.mean() - want
            lo, hi = _neighbours(s, want)
            assert lo <= got <= hi, (method, got, want)
    # BCa moves a skewed statistic's interval right of the percentile interval, by a visible amount.
    pct = stats.percentile_interval(boots, level)
    assert bca[0] > pct[0] + 0.02 and bca[1] > pct[1] + 0.02


def test_bca_reduces_to_the_percentile_interval_without_bias_or_skew():
    """z0 = 0 (estimate at the replicates' median) and a = 0 (symmetric jackknife): BCa's
    quantile levels are the percentile interval's."""
    boots = np.linspace(-1.0, 1.0, 2001)
    jackknife = np.array([-1.0, 0.0, 1.0])
    assert stats.bca_interval(0.0, boots, jackknife, 0.9) == pytest.approx(stats.percentile_interval(boots, 0.9))
    # A point estimate below every replicate: bias correction clipped, the interval stays finite
    # and at the low end of the replicates.
    lo, hi = stats.bca_interval(-5.0, boots, jackknife, 0.9)
    assert np.isfinite([lo, hi]).all() and -1.0 <= lo <= hi < -0.9


def test_bca_clips_the_bias_correction_at_half_a_replicate_by_hand():
    """An estimate above all r replicates: p = 1 is clipped to 1 - 0.5 / r, so z0 = Phi^-1(1 -
    0.5 / r); with a = 0 the quantile levels are Phi(2 z0 + z_alpha) (Efron 1987). A constant
    jackknife (no spread: acceleration 0 by the guard, not 0 / 0) gives the same interval."""
    from scipy.stats import norm

    r = 20
    boots = np.arange(1.0, r + 1.0)[::-1]
    z0 = norm.ppf(1 - 0.5 / r)
    levels = [norm.cdf(2 * z0 + norm.ppf(q)) for q in (0.05, 0.95)]
    want = np.quantile(np.sort(boots), levels, method="inverted_cdf")
    got = stats.bca_interval(100.0, boots, np.array([-1.0, 0.0, 1.0]), 0.9)
    assert got == pytest.approx(tuple(want)) and got != pytest.approx(stats.percentile_interval(boots, 0.9))
    assert stats.bca_interval(100.0, boots, np.full(4, 3.0), 0.9) == pytest.approx(got)


def test_subsample_interval_by_hand():
    """Politis & Romano: [est - s (q_hi - est), est - s (q_lo - est)]; replicates 1..99 (q at
    level 0.9 by inverted cdf: 5 and 95), est 60, s 0.5 -> [60 - 17.5, 60 + 27.5]."""
    samples = np.arange(1.0, 100.0)[::-1]
    assert stats.subsample_interval(60.0, samples, 0.9, 0.5) == pytest.approx((42.5, 87.5))
    assert stats.basic_interval(60.0, samples, 0.9) == pytest.approx((25.0, 115.0))
    assert stats.percentile_interval(samples, 0.9) == pytest.approx((5.0, 95.0))


def test_compare_per_sequence_defaults_to_sequences_and_is_seeded():
    """Without `unit` the clusters are sequences (the notes say so), and the Student-t fit is
    seeded: two calls give the same posterior to the last digit."""
    a, b = np.array([0.30, 0.32, 0.35, 0.31, 0.29, 0.33]), np.array([0.40, 0.41, 0.37, 0.45, 0.38, 0.42])
    one = comparison.compare_per_sequence(a, b, "lpips", **_FAST)
    two = comparison.compare_per_sequence(a, b, "lpips", **_FAST)
    assert "per-sequence" in one["bayes"]["estimand"] and "per-scene" not in one["bayes"]["estimand"]
    assert one["bayes"]["fitted"] and one["bayes"]["hdi"] == two["bayes"]["hdi"]
    assert one["bayes"]["mu_mean"] == two["bayes"]["mu_mean"]
    few = comparison.compare_per_sequence(a[:3], b[:3], "lpips", **_FAST)
    assert few["interval_note"] == "too few sequences (K=3)" and few["bayes"]["note"] == "too few sequences (K=3)"


def test_scene_of_and_resample_indices_edges():
    assert stats.scene_of("test-0-lane01/yaw045") == "test-0-lane01"
    assert stats.scene_of("town/test-0-lane01/yaw045") == "town/test-0-lane01"  # the last '/' splits
    assert stats.resample_indices(3, 1, seed=0).shape == (1, 3)
    for k, r in [(0, 5), (3, 0)]:
        with pytest.raises(AssertionError):
            stats.resample_indices(k, r, seed=0)


def test_stored_replicates_are_used_only_when_made_the_way_compare_resamples():
    """A results file's replicates stand in for recomputation only if every resampling setting
    matches (interval method, resamples, seed, cluster unit, cluster count) and there is one per
    resample; any single difference means recomputing."""
    from types import SimpleNamespace

    st = SimpleNamespace(bootstrap_resamples=4, seed=7)
    good = {"interval": stats.INTERVAL_METHOD, "resamples": 4, "seed": 7, "cluster": "scene", "clusters": 8}
    reps = [1.0, 2.0, 3.0, 4.0]
    assert comparison._usable_replicates({"statistics": good}, {"replicates": reps}, st, "scene", 8) == reps
    for key, other in [("interval", "bootstrap"), ("resamples", 5), ("seed", 8), ("cluster", "sequence"),
                       ("clusters", 9)]:
        doc = {"statistics": {**good, key: other}}
        assert comparison._usable_replicates(doc, {"replicates": reps}, st, "scene", 8) is None, key
    assert comparison._usable_replicates({"statistics": good}, {"replicates": reps[:3]}, st, "scene", 8) is None
    assert comparison._usable_replicates({"statistics": good}, {"replicates": tuple(reps)}, st, "scene", 8) is None
    assert comparison._usable_replicates({}, {"replicates": reps}, st, "scene", 8) is None


def test_interval_about_a_centre_is_widened_to_the_estimate():
    """FD∞'s interval (issue 39): the draws are reflected about `centre`, not the estimate, and the
    interval then widened to hold the estimate; no centre (or a non-finite one) is the estimate."""
    reps = np.array([9.0, 10.0, 11.0, 12.0, 13.0])  # K = 4: half-sampling scale sqrt(2 / 2) = 1
    lo, hi, widened = stats.interval_from_replicates(10.0, reps, 0.6, 4, centre=11.0)
    # draws 2 * 11 - reps = 13 12 11 10 9: their 20% and 80% points (the smallest draw whose share
    # of draws at or below it reaches the level) are 9 and 12; about the estimate 10 they are 7 and 10
    assert (lo, hi, widened) == (9.0, 12.0, False)
    assert stats.interval_from_replicates(10.0, reps, 0.6, 4)[:2] == (7.0, 10.0)
    lo, hi, widened = stats.interval_from_replicates(20.0, reps, 0.6, 4, centre=11.0)
    assert (lo, hi, widened) == (9.0, 20.0, True)  # the estimate outside the draws: reached
    assert stats.interval_from_replicates(10.0, reps, 0.6, 4, centre=None) == \
        stats.interval_from_replicates(10.0, reps, 0.6, 4) == stats.interval_from_replicates(10.0, reps, 0.6, 4,
                                                                                              centre=math.nan)
