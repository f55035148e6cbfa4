"""Honest statistics for results: clustered resampling intervals and a paired comparison of
two methods (same estimand for A, B and A - B).

**Clusters.** Frames of a sequence are correlated and the 8 sequences of one scene (a lane)
share one fitted model, so the protocol's `[statistics] cluster` names the independent unit:
"scene" (synthtown@2 and later) or "sequence" (synthtown@1, kept as it was). With fewer than
`MIN_CLUSTERS` clusters no interval or P(better) is given ("too few scenes (K=2)").

**Intervals** (`INTERVAL_METHOD`): half-sampling. Each of R replicates draws m = K // 2 clusters
*without* replacement (indices depend only on seed, R and K: `replicate_counts`) and recomputes
the metric on them: the per-frame mean over their frames, or the set metric (FID, KID, FVD, KVD)
from their features. With s = sqrt(m / (K - m)) (the delete-d jackknife scale, which makes the
spread of a mean's half-sample values that of the full-sample mean), the draws
est - s (theta_r - est) stand for the sampling law of est; the interval is their percentile
interval, widened to contain est when it does not (then said in a note). Without replacement
no frame is repeated, so set metrics are not inflated by duplicates (the percentile bootstrap's
failure), and the shift theta_m - est corrects the 1/N small-sample bias of FID/KID to first
order. `bench/coverage.py` measures this against percentile, basic and BCa bootstrap intervals
(docs/evaluate.md has the table).

Pure functions on arrays; no file I/O here. The paired comparison of two results files is in
`comparison`, the Student-t model in `bayes`; which metric is better higher or lower, and which
resampling a set metric uses, comes from `metricspec`.
"""

from __future__ import annotations

import math

import numpy as np

from .metricspec import METRICS, metric_def

#: Metrics of the table at import for which a lower value is better (everything else: higher is better).
LOWER_IS_BETTER = frozenset(n for n, m in METRICS.items() if not m.higher_is_better)


def higher_is_better(metric: str) -> bool:
    """The table's direction of `metric`, read when asked (a metric registered later has one); an
    unknown name: higher is better."""
    m = METRICS.get(metric)
    return True if m is None else m.higher_is_better


# --------------------------------------------------------------------------- clusters

#: Below this many clusters, intervals and P(better) are not reported (too few to mean anything).
MIN_CLUSTERS = 5
#: The interval method of every metric (results.json `statistics.interval`).
INTERVAL_METHOD = "half-sampling"


def scene_of(sequence_id: str) -> str:
    """`"test-0-lane01/yaw045"` -> `"test-0-lane01"` (data.layout: sequence id = scene/name)."""
    return sequence_id.rpartition("/")[0]


def cluster_map(sequence_ids: list[str], unit: str) -> tuple[np.ndarray, list[str]]:
    """Cluster index of each sequence, int64 [S], and the cluster names in first-seen order.

    unit "scene": every sequence of one scene (lane) is one cluster; "sequence": each its own."""
    if unit == "sequence":
        return np.arange(len(sequence_ids), dtype=np.int64), list(sequence_ids)
    assert unit == "scene", unit
    names: dict[str, int] = {}
    idx = [names.setdefault(scene_of(s), len(names)) for s in sequence_ids]
    return np.array(idx, dtype=np.int64), list(names)


def too_few(n_clusters: int, unit: str) -> str | None:
    """The reason no interval is given ("too few scenes (K=2)"), or None when there are enough."""
    return f"too few {unit}s (K={n_clusters})" if n_clusters < MIN_CLUSTERS else None


def replicate_counts(n_clusters: int, resamples: int, seed: int) -> np.ndarray:
    """The clusters of each replicate: 0/1 float64 [R, K], K // 2 ones per row (half-sampling).
    Depends only on (seed, resamples, n_clusters): two results on the same dataset and protocol
    use the same rows, so differencing replicate r of A and of B is a paired resample."""
    return subsample_counts(n_clusters, resamples, seed)


def half_scale(n_clusters: int) -> float:
    """sqrt(m / (K - m)) for m = K // 2: maps the spread of half-sample values to the full sample."""
    m = n_clusters // 2
    return math.sqrt(m / (n_clusters - m))


def replicate_draws(estimate: float, replicates, n_clusters: int) -> np.ndarray:
    """Draws standing for the sampling law of `estimate`: est - s (theta_r - est), undefined
    (None / NaN) replicates dropped. An infinite estimate (PSNR with exact frames) has no
    finite shift: its draws are the replicates themselves."""
    r = np.array([np.nan if v is None else v for v in replicates], dtype=np.float64)
    r = r[~np.isnan(r)]
    if not math.isfinite(estimate):
        return r
    with np.errstate(invalid="ignore", over="ignore"):  # values near 1e308 (hostile files): +-inf draws
        d = estimate - half_scale(n_clusters) * (r - estimate)
    return d[~np.isnan(d)]


def interval_from_replicates(estimate: float, replicates, level: float, n_clusters: int,
                             centre: float | None = None) -> tuple[float, float, bool] | None:
    """The reported interval from half-sampling replicates [R] (any metric, or a paired
    difference of two metrics' replicates): percentile interval of `replicate_draws` about
    `centre` (None: the estimate; FD∞'s is its value with the subset noise averaged out,
    `MetricDef.centre`), widened to contain `estimate`. Returns (lo, hi, widened) or None when no
    replicate is defined.

    The replicates of a paired difference are `advantage(replicates_a, replicates_b)`, element
    by element, with `estimate` = `advantage(value_a, value_b)` (and `centre` likewise)."""
    about = estimate if centre is None or not math.isfinite(centre) else centre
    d = replicate_draws(about, replicates, n_clusters)
    if not len(d):
        return None
    lo, hi = percentile_interval(d, level)
    widened = not lo <= estimate <= hi
    return min(lo, estimate), max(hi, estimate), widened


def round_replicates(values: np.ndarray) -> list[float | None]:
    """Replicates for JSON: 6 significant digits, None where undefined (NaN); +-inf kept."""
    return [None if math.isnan(v) else v if math.isinf(v) else float(f"{v:.6g}") for v in map(float, values)]


# --------------------------------------------------------------------------- resampling


def resample_indices(n_clusters: int, resamples: int, seed: int) -> np.ndarray:
    """Sequence ids drawn with replacement: int64 [R, K] for K = n_clusters."""
    assert n_clusters >= 1 and resamples >= 1
    rng = np.random.default_rng(seed)
    return rng.integers(0, n_clusters, size=(resamples, n_clusters))


def resample_counts(idx: np.ndarray, n_clusters: int) -> np.ndarray:
    """How often each cluster is drawn in each resample: float64 [R, K] from idx [R, K]."""
    r = idx.shape[0]
    counts = np.zeros((r, n_clusters))
    np.add.at(counts, (np.repeat(np.arange(r), idx.shape[1]), idx.ravel()), 1.0)
    return counts


def percentile_interval(samples: np.ndarray, level: float) -> tuple[float, float]:
    """Percentile interval of bootstrap samples [R]. +inf samples sort last (an interval may
    end at +inf); NaN samples are an error of the caller."""
    s = np.sort(np.asarray(samples, dtype=np.float64))
    assert not np.isnan(s).any(), "NaN in bootstrap samples"
    a = (1.0 - level) / 2.0
    # NOTE: 'inverted_cdf' picks actual sample values, so infinities never mix with finite
    # values in an interpolation (which would give NaN).
    lo, hi = np.quantile(s, [a, 1.0 - a], method="inverted_cdf")
    return float(lo), float(hi)


def subsample_counts(n_clusters: int, resamples: int, seed: int, m: int | None = None) -> np.ndarray:
    """Cluster subsamples without replacement: float64 0/1 [R, K], m = K // 2 ones per row.

    Depends only on (n_clusters, resamples, seed, m), like `resample_indices`."""
    assert n_clusters >= 2 and resamples >= 1
    m = n_clusters // 2 if m is None else m
    assert 1 <= m < n_clusters
    rng = np.random.default_rng([seed, n_clusters, 1])  # a stream of its own, not the bootstrap's
    ranks = np.argsort(rng.random((resamples, n_clusters)), axis=1)
    return (ranks < m).astype(np.float64)


def basic_interval(estimate: float, samples: np.ndarray, level: float) -> tuple[float, float]:
    """Basic (reflected) bootstrap interval: 2 est - q_hi, 2 est - q_lo."""
    lo, hi = percentile_interval(samples, level)
    return 2 * estimate - hi, 2 * estimate - lo


def bca_interval(estimate: float, samples: np.ndarray, jackknife: np.ndarray, level: float) -> tuple[float, float]:
    """Bias-corrected and accelerated interval (Efron 1987) from bootstrap samples [R] and
    leave-one-cluster-out values [K] (acceleration). The bias correction is clipped so that a
    point estimate below every replicate still gives a finite interval."""
    from scipy.stats import norm

    s = np.asarray(samples, np.float64)
    r = len(s)
    p = (np.sum(s < estimate) + 0.5 * np.sum(s == estimate)) / r
    z0 = norm.ppf(min(max(p, 0.5 / r), 1 - 0.5 / r))
    j = np.asarray(jackknife, np.float64)
    dev = j.mean() - j
    den = 6.0 * np.sum(dev**2) ** 1.5
    acc = float(np.sum(dev**3) / den) if den > 0 else 0.0
    a = (1.0 - level) / 2.0
    qs = []
    for z in (norm.ppf(a), norm.ppf(1 - a)):
        qs.append(float(norm.cdf(z0 + (z0 + z) / (1 - acc * (z0 + z)))))
    lo, hi = np.quantile(np.sort(s), qs, method="inverted_cdf")
    return float(lo), float(hi)


def subsample_interval(estimate: float, samples: np.ndarray, level: float, scale: float) -> tuple[float, float]:
    """Subsampling interval (Politis & Romano 1994) from subsample values [R]: the law of
    scale * (theta_m - est) stands in for that of (est - theta):
    [est - scale (q_hi - est), est - scale (q_lo - est)]."""
    lo, hi = percentile_interval(samples, level)
    return estimate - scale * (hi - estimate), estimate - scale * (lo - estimate)


def frame_metric_samples(values: np.ndarray, clusters: np.ndarray, counts: np.ndarray,
                         weights: np.ndarray | None = None, pool: str = "mean") -> np.ndarray:
    """Mean of per-frame values over each resample's frames.

    Args:
        values: [N] per-frame values (may hold +inf, e.g. PSNR of an exact frame).
        clusters: [N] int, the sequence id (0..K-1) of each frame.
        counts: [R, K] how often each sequence is drawn.
        weights: [N] pixel counts of a pixel-weighted metric (`metricspec.MetricDef.weighted`), or
            None: every frame counts once. With weights, frames of weight 0 (NaN values) are left
            out and the frames are pooled by `pool`: "mean", sum(w v) / sum(w); "mse" (PSNR
            values), -10 log10(sum(w 10^(-v/10)) / sum(w)), the PSNR of the pooled squared error.
    Returns:
        [R] resampled means; +inf where a drawn sequence holds an infinite value (unweighted);
        NaN where the drawn frames hold no weight.
    """
    if weights is not None:
        return _pooled_samples(values, clusters, counts, weights, pool)
    values = np.asarray(values, dtype=np.float64)
    k = counts.shape[1]
    n_per = np.bincount(clusters, minlength=k).astype(np.float64)
    inf_per = np.bincount(clusters, weights=np.isposinf(values), minlength=k) > 0
    ninf_per = np.bincount(clusters, weights=np.isneginf(values), minlength=k) > 0
    sums = np.bincount(clusters, weights=np.where(np.isfinite(values), values, 0.0), minlength=k)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (counts @ sums) / (counts @ n_per)
    pos = (counts[:, inf_per] > 0).any(axis=1)
    neg = (counts[:, ninf_per] > 0).any(axis=1)
    out[pos] = np.inf
    out[neg] = -np.inf
    out[pos & neg] = np.nan  # +inf and -inf in one mean: undefined (not produced by our metrics)
    return out


def _pooled_samples(values, clusters, counts, weights, pool: str) -> np.ndarray:
    assert pool in ("mean", "mse"), pool
    v = np.asarray(values, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    use = (w > 0) & ~np.isnan(v)
    with np.errstate(over="ignore"):
        t = v if pool == "mean" else np.power(10.0, -v / 10.0)  # PSNR -> MSE (+inf -> 0)
    w = np.where(use, w, 0.0)
    k = counts.shape[1]
    num = np.bincount(clusters, weights=w * np.where(use, t, 0.0), minlength=k)
    den = np.bincount(clusters, weights=w, minlength=k)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (counts @ num) / (counts @ den)  # 0 / 0 -> NaN: no weight drawn
        return out if pool == "mean" else -10.0 * np.log10(out)


def pooled_value(values: np.ndarray, weights: np.ndarray | None, pool: str = "mean") -> float:
    """The summary of per-frame values [N] over all frames, as `frame_metric_samples` pools them."""
    values = np.asarray(values, dtype=np.float64)
    one = np.zeros(len(values), dtype=np.int64)
    return float(frame_metric_samples(values, one, np.ones((1, 1)), weights, pool)[0])


def sequence_psnr(psnrs: np.ndarray, clusters: np.ndarray, k: int) -> np.ndarray:
    """Per-sequence PSNR from the sequence's mean MSE: [K] from per-frame PSNR [N].

    This is finite unless every frame of the sequence is exact (then +inf), which is what makes
    per-sequence differences between two methods usable in a paired comparison.
    """
    mse = np.power(10.0, -np.asarray(psnrs, dtype=np.float64) / 10.0)  # +inf PSNR -> MSE 0
    mean_mse = np.bincount(clusters, weights=mse, minlength=k) / np.bincount(clusters, minlength=k)
    with np.errstate(divide="ignore"):
        return -10.0 * np.log10(mean_mse)


# --------------------------------------------------------------------------- set metrics


class FrechetBootstrap:
    """Fréchet distance between two feature sets under resampling weights, recomputed exactly
    per resample from Gram matrices computed once.

    With A = W1^(1/2) (X1 - mu1) / sqrt(n1 - 1) (so cov1 = A^T A) and B likewise,
    tr sqrtm(cov1 cov2) equals the nuclear norm of A B^T (the nonzero eigenvalues of
    A^T A B^T B are those of (A B^T)(A B^T)^T). When frames are fewer than feature dimensions
    this works in frame space (N x N) instead of D x D; otherwise on covariances directly.
    """

    def __init__(self, x1: np.ndarray, x2: np.ndarray):
        # x1: [N1, D] submission features; x2: [N2, D] ground-truth features
        self.x1 = np.asarray(x1, dtype=np.float64)
        self.x2 = np.asarray(x2, dtype=np.float64)
        assert self.x1.ndim == 2 and self.x2.ndim == 2 and self.x1.shape[1] == self.x2.shape[1]
        self.d = self.x1.shape[1]
        self.gram = max(len(self.x1), len(self.x2)) <= self.d
        if self.gram:
            self.g11 = self.x1 @ self.x1.T  # [N1, N1]
            self.g22 = self.x2 @ self.x2.T  # [N2, N2]
            self.g12 = self.x1 @ self.x2.T  # [N1, N2]

    @classmethod
    def from_features(cls, sub: np.ndarray, gt: np.ndarray, seq: np.ndarray, n_clusters: int, *_) -> FrechetBootstrap:
        """The metric table's bootstrap factory (`set_metric_bootstrap`); rows are weighted one by one."""
        return cls(sub, gt)

    def __call__(self, w1: np.ndarray, w2: np.ndarray) -> float:
        """FID for row weights w1 [N1], w2 [N2] (resample multiplicities; zero rows dropped)."""
        w1 = np.asarray(w1, dtype=np.float64)
        w2 = np.asarray(w2, dtype=np.float64)
        n1, n2 = w1.sum(), w2.sum()
        if n1 < 2 or n2 < 2:
            return math.nan
        if not self.gram:
            return self._covariance_route(w1, w2, n1, n2)
        k1, k2 = np.flatnonzero(w1), np.flatnonzero(w2)
        w1, w2 = w1[k1], w2[k2]
        g11 = self.g11[np.ix_(k1, k1)]
        g22 = self.g22[np.ix_(k2, k2)]
        g12 = self.g12[np.ix_(k1, k2)]
        mu11 = w1 @ g11 @ w1 / n1**2  # |mu1|^2
        mu22 = w2 @ g22 @ w2 / n2**2
        mu12 = w1 @ g12 @ w2 / (n1 * n2)
        tr1 = (w1 @ np.diag(g11) - n1 * mu11) / (n1 - 1)
        tr2 = (w2 @ np.diag(g22) - n2 * mu22) / (n2 - 1)
        # centred cross Gram (X1 - mu1)(X2 - mu2)^T
        c = g12 - (g12 @ w2 / n2)[:, None] - (w1 @ g12 / n1)[None, :] + mu12
        m = np.sqrt(w1)[:, None] * c * np.sqrt(w2)[None, :] / math.sqrt((n1 - 1) * (n2 - 1))
        mm = m @ m.T if m.shape[0] <= m.shape[1] else m.T @ m
        tr_sqrt = np.sqrt(np.clip(np.linalg.eigvalsh(mm), 0.0, None)).sum()
        # the exact value is >= 0; below 0 is rounding (as metrics.frechet_distance clamps)
        return max(float(mu11 + mu22 - 2 * mu12 + tr1 + tr2 - 2 * tr_sqrt), 0.0)

    def _covariance_route(self, w1, w2, n1, n2) -> float:
        mu1 = w1 @ self.x1 / n1
        mu2 = w2 @ self.x2 / n2
        c1 = self.x1 - mu1
        c2 = self.x2 - mu2
        s1 = (c1 * w1[:, None]).T @ c1 / (n1 - 1)
        s2 = (c2 * w2[:, None]).T @ c2 / (n2 - 1)
        return frechet_eigh(mu1, s1, mu2, s2)


def frechet_eigh(mu1: np.ndarray, s1: np.ndarray, mu2: np.ndarray, s2: np.ndarray) -> float:
    """Fréchet distance via symmetric eigendecompositions (stable for PSD covariances [D, D]):
    tr sqrtm(s1 s2) = tr sqrtm(s1^(1/2) s2 s1^(1/2))."""
    lam, v = np.linalg.eigh(s1)
    r1 = (v * np.sqrt(np.clip(lam, 0.0, None))) @ v.T
    inner = np.linalg.eigvalsh(r1 @ s2 @ r1)
    tr_sqrt = np.sqrt(np.clip(inner, 0.0, None)).sum()
    diff = mu1 - mu2
    return max(float(diff @ diff + np.trace(s1) + np.trace(s2) - 2 * tr_sqrt), 0.0)


def polynomial_kernel(x: np.ndarray, y: np.ndarray, *, degree: int = 3, gamma: float | None = None,
                      coef0: float = 1.0) -> np.ndarray:
    """k(x, y) = (gamma x.y + coef0)^degree, gamma = 1/D by default (KID, Bińkowski et al. 2018).

    x: [N, D], y: [M, D] -> [N, M]."""
    gamma = 1.0 / x.shape[1] if gamma is None else gamma
    return (gamma * (np.asarray(x, np.float64) @ np.asarray(y, np.float64).T) + coef0) ** degree


class MMDBootstrap:
    """Unbiased MMD^2 (polynomial kernel) under sequence resampling, from per-sequence kernel
    block sums computed once by streaming over row chunks: memory O(K^2 + chunk x N), not
    O(N^2). A frame drawn c times counts as c distinct samples; the U-statistic leaves out only
    identical instances (i == j), not copies of the same frame.

    NOTE: the point estimate of KID/KVD follows the protocol (mean over random subsets of at
    most `subset_size`; with no more rows than that, the full-sample estimate); the bootstrap
    recomputes the full-sample unbiased MMD^2, the quantity that subset average estimates.
    """

    by_cluster = True  # called with per-sequence counts, not per-row weights
    _CHUNK = 1024

    def __init__(self, x: np.ndarray, y: np.ndarray, clusters_x: np.ndarray, clusters_y: np.ndarray,
                 n_clusters: int, *, degree: int = 3, gamma: float | None = None, coef0: float = 1.0):
        # x: [N1, D] submission features, y: [N2, D] ground truth; clusters_*: [N*] sequence ids
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        kw = dict(degree=degree, gamma=1.0 / x.shape[1] if gamma is None else gamma, coef0=coef0)
        k = n_clusters
        self.nx = np.bincount(clusters_x, minlength=k).astype(np.float64)
        self.ny = np.bincount(clusters_y, minlength=k).astype(np.float64)
        self.sxx, self.dxx = self._block_sums(x, x, clusters_x, clusters_x, k, kw)
        self.syy, self.dyy = self._block_sums(y, y, clusters_y, clusters_y, k, kw)
        self.sxy, _ = self._block_sums(x, y, clusters_x, clusters_y, k, kw, diag=False)

    @classmethod
    def from_features(cls, sub: np.ndarray, gt: np.ndarray, seq: np.ndarray, n_clusters: int, *_) -> MMDBootstrap:
        """The metric table's bootstrap factory: sub [N, D] and gt [N, D] rows of sequences seq [N]."""
        return cls(sub, gt, seq, seq, n_clusters)

    def _block_sums(self, a, b, ca, cb, k, kw, diag=True):
        onehot_b = np.zeros((len(b), k))
        onehot_b[np.arange(len(b)), cb] = 1.0
        blocks = np.zeros((k, k))
        d = np.zeros(k)
        for s in range(0, len(a), self._CHUNK):
            kc = polynomial_kernel(a[s:s + self._CHUNK], b, **kw)  # [c, N2]
            per_col = kc @ onehot_b  # [c, K]
            np.add.at(blocks, ca[s:s + self._CHUNK], per_col)
            if diag:
                rows = np.arange(s, min(s + self._CHUNK, len(a)))
                d += np.bincount(ca[rows], weights=kc[rows - s, rows], minlength=k)
        return blocks, d

    def __call__(self, c1: np.ndarray, c2: np.ndarray) -> float:
        """MMD^2 for per-sequence counts c1 (submission side) and c2 (ground truth), [K] each."""
        n, m = c1 @ self.nx, c2 @ self.ny
        if n < 2 or m < 2:
            return math.nan
        sxx = c1 @ self.sxx @ c1 - c1 @ self.dxx
        syy = c2 @ self.syy @ c2 - c2 @ self.dyy
        sxy = c1 @ self.sxy @ c2
        return float(sxx / (n * (n - 1)) + syy / (m * (m - 1)) - 2 * sxy / (n * m))


def set_metric_bootstrap(metric: str, sub, gt, seq, n_clusters: int, settings=None, seed: int = 0):
    """The resampled version of a set metric, as its `metricspec` entry names it.

    Args:
        metric: a set metric's name ("fid", "kid", ...).
        sub: [N, D] submission features; gt: [N, D] ground-truth features of the same frames / clips.
        seq: [N] sequence id (0..n_clusters-1) of each row. settings, seed: the protocol's MetricSpec and seed (FID∞).
    Returns:
        A callable for `set_metric_samples` (FrechetBootstrap, MMDBootstrap, ...).
    """
    from .registry import load_entry_point

    spec = metric_def(metric)
    assert spec.kind == "set" and spec.bootstrap, metric
    return load_entry_point(spec.bootstrap)(sub, gt, seq, n_clusters, settings, seed)


def set_metric_samples(fn, clusters1: np.ndarray, clusters2: np.ndarray, counts: np.ndarray,
                       progress=None) -> np.ndarray:
    """Evaluate a weighted set metric `fn(w1, w2)` for each resample.

    Args:
        fn: FrechetBootstrap or MMDBootstrap (or any callable on row weights).
        clusters1: [N1] sequence id of each submission feature row; clusters2: [N2] ground truth.
        counts: [R, K] resample multiplicities of each sequence.
        progress: optional callable advanced once per resample.
    Returns:
        [R] metric values.

    A resample drawn twice is computed once: half-sampling K scenes has only C(K, K // 2)
    distinct draws (70 for K = 8), so most of R = 1000 replicates repeat one, and one Fréchet
    replicate on 2048-d Inception features costs an eigendecomposition.
    """
    out = np.empty(counts.shape[0])
    by_cluster = getattr(fn, "by_cluster", False)
    seen: dict[bytes, float] = {}
    for r, c in enumerate(counts):
        key = np.ascontiguousarray(c).tobytes()
        if key not in seen:
            seen[key] = fn(c, c) if by_cluster else fn(c[clusters1], c[clusters2])
        out[r] = seen[key]
        if progress is not None:
            progress(1)
    return out


# --------------------------------------------------------------------------- paired comparison


def advantage(a: np.ndarray, b: np.ndarray, metric: str) -> np.ndarray:
    """Signed difference so that > 0 means A is better: A - B if higher is better, else B - A.

    Infinities (PSNR of exactly reproduced sequences): inf - inf (both exact) is a tie, 0;
    inf - finite is +inf (A exact, B not) and stays infinite.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        d = a - b if higher_is_better(metric) else b - a
    both = np.isinf(a) & np.isinf(b) & (np.sign(a) == np.sign(b))
    return np.where(both, 0.0, d)


def advantage_interval(d: np.ndarray, *, resamples: int, level: float, seed: int) -> tuple[float, float] | None:
    """Interval of the mean of per-cluster advantages d [K], each cluster weighted equally: the
    half-sampling interval `compare_per_sequence` reports. None below MIN_CLUSTERS clusters or
    when d holds NaN (no interval exists)."""
    k = len(d)
    if k < MIN_CLUSTERS or np.isnan(d).any():
        return None
    mean = float(np.mean(d))
    reps = frame_metric_samples(d, np.arange(k), replicate_counts(k, resamples, seed))
    iv = interval_from_replicates(mean, reps, level, k)
    return None if iv is None else (iv[0], iv[1])
