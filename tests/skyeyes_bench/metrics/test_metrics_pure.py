"""PSNR, SSIM, Frechet distance, polynomial MMD and FeatureStats against independent computations."""

import numpy as np
import pytest
import scipy.linalg
from skimage.metrics import structural_similarity

from skyeyes_bench.metrics import FeatureStats, frechet_distance, kernel_mmd, psnr, ssim


def _imgs(seed, shape):
    rng = np.random.default_rng(seed)
    return rng.random(shape).astype(np.float32)


# --------------------------------------------------------------------------- PSNR


def test_psnr_by_hand_and_leading_dims():
    a, b = _imgs(0, (2, 3, 16, 20, 3)), _imgs(1, (2, 3, 16, 20, 3))
    got = psnr(a, b)
    assert got.shape == (2, 3)
    for i in range(2):
        for j in range(3):
            mse = sum((float(x) - float(y)) ** 2 for x, y in zip(a[i, j].ravel(), b[i, j].ravel())) / a[i, j].size
            assert got[i, j] == pytest.approx(10 * np.log10(1 / mse), rel=1e-12)


def test_psnr_identical_is_inf_and_known_value():
    a = _imgs(2, (8, 8, 3))
    assert psnr(a, a) == np.inf
    b = np.full((8, 8, 3), 0.5)
    c = b + 0.1  # MSE 0.01 -> 20 dB
    assert psnr(c, b) == pytest.approx(20.0, abs=1e-9)


def test_psnr_shape_mismatch_raises():
    with pytest.raises(ValueError):
        psnr(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))


# --------------------------------------------------------------------------- SSIM


@pytest.mark.parametrize("shape", [(32, 40, 3), (11, 11, 3), (64, 48, 3)])
def test_ssim_matches_skimage_wang_settings(shape):
    rng = np.random.default_rng(3)
    gt = rng.random(shape)
    pred = np.clip(gt + rng.normal(0, 0.1, shape), 0, 1)
    ref = structural_similarity(pred, gt, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                data_range=1.0, channel_axis=-1)
    assert ssim(pred, gt) == pytest.approx(ref, abs=1e-10)


def test_ssim_batched_and_identity():
    rng = np.random.default_rng(4)
    gt = rng.random((3, 24, 24, 3))
    pred = np.clip(gt * 0.8 + 0.1, 0, 1)
    got = ssim(pred, gt)
    assert got.shape == (3,)
    for i in range(3):
        ref = structural_similarity(pred[i], gt[i], gaussian_weights=True, sigma=1.5,
                                    use_sample_covariance=False, data_range=1.0, channel_axis=-1)
        assert got[i] == pytest.approx(ref, abs=1e-10)
    assert np.allclose(ssim(gt, gt), 1.0)


# --------------------------------------------------------------------------- Frechet


def _fd_scipy(mu1, s1, mu2, s2):
    covmean = scipy.linalg.sqrtm(s1 @ s2)
    covmean = covmean.real
    return float(((mu1 - mu2) ** 2).sum() + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean))


def _rand_cov(rng, d, n):
    x = rng.normal(size=(n, d)) @ rng.normal(size=(d, d))
    return x.mean(0), np.cov(x, rowvar=False)


def test_frechet_matches_scipy_sqrtm_well_conditioned():
    rng = np.random.default_rng(5)
    for d in (3, 16, 64):
        mu1, s1 = _rand_cov(rng, d, 10 * d)
        mu2, s2 = _rand_cov(rng, d, 10 * d)
        ref = _fd_scipy(mu1, s1, mu2, s2)
        assert frechet_distance(mu1, s1, mu2, s2) == pytest.approx(ref, rel=1e-8, abs=1e-8)


def test_frechet_closed_form_diagonal():
    rng = np.random.default_rng(6)
    d = 50
    a, b = rng.random(d) * 3, rng.random(d) * 3
    mu1, mu2 = rng.normal(size=d), rng.normal(size=d)
    ref = ((mu1 - mu2) ** 2).sum() + ((np.sqrt(a) - np.sqrt(b)) ** 2).sum()
    assert frechet_distance(mu1, np.diag(a), mu2, np.diag(b)) == pytest.approx(ref, rel=1e-12)


def test_frechet_identical_sets_is_zero_even_rank_deficient():
    rng = np.random.default_rng(7)
    for n, d in [(500, 20), (10, 64)]:  # the second has n < d: rank 9 covariance
        x = rng.normal(size=(n, d)) * rng.random(d) * 5
        mu, s = x.mean(0), np.cov(x, rowvar=False)
        val = frechet_distance(mu, s, mu, s)
        assert 0.0 <= val < 1e-9 * max(1.0, np.trace(s))


def test_frechet_rank_deficient_against_closed_form():
    # Two rank-deficient covariances sharing eigenvectors: closed form sum (sqrt a - sqrt b)^2.
    rng = np.random.default_rng(8)
    d = 40
    q, _ = np.linalg.qr(rng.normal(size=(d, d)))
    a = np.where(np.arange(d) < 10, rng.random(d) + 0.5, 0.0)
    b = np.where(np.arange(d) < 15, rng.random(d) + 0.5, 0.0)
    s1, s2 = q @ np.diag(a) @ q.T, q @ np.diag(b) @ q.T
    mu = np.zeros(d)
    ref = ((np.sqrt(a) - np.sqrt(b)) ** 2).sum()
    assert frechet_distance(mu, s1, mu, s2) == pytest.approx(ref, rel=1e-9, abs=1e-9)


def test_frechet_scale_and_offset_stiff():
    rng = np.random.default_rng(9)
    d = 8
    a, b = rng.random(d) + 0.1, rng.random(d) + 0.1
    q, _ = np.linalg.qr(rng.normal(size=(d, d)))
    s1, s2 = q @ np.diag(a) @ q.T, q @ np.diag(b) @ q.T
    base = ((np.sqrt(a) - np.sqrt(b)) ** 2).sum()
    # Scale 1e6 on the features: distance scales by 1e12.
    k = 1e6
    got = frechet_distance(np.zeros(d), s1 * k * k, np.zeros(d), s2 * k * k)
    assert got == pytest.approx(base * k * k, rel=1e-6)
    # Offset 1e6 on both means: distance unchanged.
    off = np.full(d, 1e6)
    dm = rng.normal(size=d)
    got = frechet_distance(off, s1, off + dm, s2)
    assert got == pytest.approx(base + dm @ dm, rel=1e-9)
    # Identical at scale 1e6: zero up to rounding, never negative.
    val = frechet_distance(np.zeros(d), s1 * k * k, np.zeros(d), s1 * k * k)
    assert 0.0 <= val <= 1e-9 * np.trace(s1) * k * k


def test_frechet_near_singular_covariance():
    rng = np.random.default_rng(10)
    d = 30
    x = rng.normal(size=(200, d))
    x[:, 1] = x[:, 0] + 1e-9 * rng.normal(size=200)  # nearly collinear columns
    y = rng.normal(size=(200, d)) * 1.5
    mu1, s1, mu2, s2 = x.mean(0), np.cov(x, rowvar=False), y.mean(0), np.cov(y, rowvar=False)
    got = frechet_distance(mu1, s1, mu2, s2)
    assert np.isfinite(got) and got >= 0
    # Reference in extended care: scipy sqrtm of the same product (well enough conditioned here).
    assert got == pytest.approx(_fd_scipy(mu1, s1, mu2, s2), rel=1e-6)


# --------------------------------------------------------------------------- MMD


def _mmd_loops(x, y, degree=3, gamma=None, coef0=1.0):
    d = x.shape[1]
    g = 1.0 / d if gamma is None else gamma

    def k(a, b):
        return (g * float(np.dot(a, b)) + coef0) ** degree

    n, m = len(x), len(y)
    sxx = sum(k(x[i], x[j]) for i in range(n) for j in range(n) if i != j) / (n * (n - 1))
    syy = sum(k(y[i], y[j]) for i in range(m) for j in range(m) if i != j) / (m * (m - 1))
    sxy = sum(k(x[i], y[j]) for i in range(n) for j in range(m)) / (n * m)
    return sxx + syy - 2 * sxy


def test_kernel_mmd_against_double_loop():
    rng = np.random.default_rng(11)
    x, y = rng.normal(size=(17, 5)), rng.normal(0.3, 1.2, size=(13, 5))
    assert kernel_mmd(x, y) == pytest.approx(_mmd_loops(x, y), rel=1e-10)
    assert kernel_mmd(x, y, degree=2, gamma=0.5, coef0=0.0) == pytest.approx(
        _mmd_loops(x, y, 2, 0.5, 0.0), rel=1e-10)


def test_kernel_mmd_subsets_mean_of_loops():
    rng = np.random.default_rng(12)
    x, y = rng.normal(size=(30, 4)), rng.normal(0.5, 1.0, size=(25, 4))
    got = kernel_mmd(x, y, subset_size=10, num_subsets=3, seed=7)
    r = np.random.default_rng(7)
    vals = []
    for _ in range(3):
        xi = x[r.choice(30, 10, replace=False)]
        yi = y[r.choice(25, 10, replace=False)]
        vals.append(_mmd_loops(xi, yi))
    assert got == pytest.approx(np.mean(vals), rel=1e-10)


def test_kernel_mmd_same_distribution_near_zero_and_shift_positive():
    rng = np.random.default_rng(13)
    x, y = rng.normal(size=(2000, 16)), rng.normal(size=(2000, 16))
    same = kernel_mmd(x, y, subset_size=1000, num_subsets=20)
    shifted = kernel_mmd(x, y + 0.5, subset_size=1000, num_subsets=20)
    assert abs(same) < 0.02 * shifted
    assert shifted > 0


# --------------------------------------------------------------------------- FeatureStats


def test_featurestats_mean_cov_merge_roundtrip(tmp_path):
    rng = np.random.default_rng(14)
    x = rng.normal(3.0, 2.0, size=(300, 6))
    a = FeatureStats(6).update(x[:100]).update(x[100:170])
    b = FeatureStats(6).update(x[170:])
    m = a.merge(b)
    assert m.n == 300
    assert np.allclose(m.mean(), x.mean(0), rtol=1e-12)
    assert np.allclose(m.cov(), np.cov(x, rowvar=False), rtol=1e-10, atol=1e-12)
    assert np.allclose(m.cov(biased=True), np.cov(x, rowvar=False, bias=True), rtol=1e-10, atol=1e-12)
    # merge is exact: same sums as adding the shards' sums
    assert np.array_equal(m.outer, a.outer + b.outer) and np.array_equal(m.sum, a.sum + b.sum)
    for name in ("s.json", "s.npz"):
        m.save(tmp_path / name)
        r = FeatureStats.load(tmp_path / name)
        assert r.n == m.n and np.array_equal(r.sum, m.sum) and np.array_equal(r.outer, m.outer)
    r = FeatureStats.from_dict(__import__("json").loads(__import__("json").dumps(m.to_dict())))
    assert np.array_equal(r.outer, m.outer)


def test_featurestats_rejects_wrong_dim():
    with pytest.raises(AssertionError):
        FeatureStats(4).update(np.zeros((3, 5)))


def test_frechet_zero_covariance():
    rng = np.random.default_rng(15)
    d = 12
    mu1, s2 = _rand_cov(rng, d, 100)
    mu2 = rng.normal(size=d)
    ref = ((mu1 - mu2) ** 2).sum() + np.trace(s2)
    assert frechet_distance(mu1, np.zeros((d, d)), mu2, s2) == pytest.approx(ref, rel=1e-12)
    assert frechet_distance(mu2, s2, mu1, np.zeros((d, d))) == pytest.approx(ref, rel=1e-12)


def test_kernel_mmd_gram_path_equals_subset_path(monkeypatch):
    import skyeyes_bench.metrics.sets as sets

    rng = np.random.default_rng(16)
    x, y = rng.normal(size=(60, 8)), rng.normal(0.2, 1.0, size=(50, 8))
    fast = kernel_mmd(x, y, subset_size=20, num_subsets=7, seed=3)
    monkeypatch.setattr(sets, "_GRAM_LIMIT", 0)
    slow = kernel_mmd(x, y, subset_size=20, num_subsets=7, seed=3)
    assert fast == pytest.approx(slow, rel=1e-10)


def test_kernel_mmd_at_two_samples_and_unequal_sets():
    """Two rows a side is enough for the unbiased estimate; subsets never exceed the smaller set
    (5 rows against 12 with subset_size 8: every subset of x is all of x)."""
    rng = np.random.default_rng(14)
    x, y = rng.normal(size=(5, 3)), rng.normal(0.4, size=(12, 3))
    assert kernel_mmd(x[:2], y[:2]) == pytest.approx(_mmd_loops(x[:2], y[:2]), rel=1e-10)
    with pytest.raises(ValueError, match="at least 2"):
        kernel_mmd(x[:2], y[:1])
    got = kernel_mmd(x, y, subset_size=8, num_subsets=4, seed=3)
    r = np.random.default_rng(3)
    vals = []
    for _ in range(4):
        xi = x[r.choice(5, 5, replace=False)]
        vals.append(_mmd_loops(xi, y[r.choice(12, 5, replace=False)]))
    assert got == pytest.approx(np.mean(vals), rel=1e-10)
    with pytest.raises(AssertionError):
        kernel_mmd(x, rng.normal(size=(6, 4)))  # feature dimensions differ


def test_random_extractors_take_any_float_or_8bit_input():
    """The test-only extractors cast what they are given (float64, uint8 in [0, 1]) to float32."""
    from skyeyes_bench.metrics.extractors import get_extractor

    rng = np.random.default_rng(15)
    img = rng.random((2, 64, 64, 3))
    clip = rng.random((1, 4, 64, 64, 3))
    for ex_id, a in (("random-image-64", img), ("random-video-64", clip)):
        ex = get_extractor(ex_id)
        f32 = ex.features(a.astype(np.float32))
        np.testing.assert_allclose(ex.features(a), f32, rtol=1e-6)
        np.testing.assert_allclose(ex.features((a > 0.5).astype(np.uint8)), ex.features((a > 0.5).astype(np.float32)))


def test_assert_official_names_unknown_and_test_only_extractors():
    from skyeyes_bench.errors import UserError
    from skyeyes_bench.metrics.extractors import assert_official

    with pytest.raises(UserError, match="unknown extractor .nope.; known: i3d"):
        assert_official("nope")
    with pytest.raises(UserError, match="test-only"):
        assert_official("random-image-64")
    assert_official("inception-tf-2015") is None
