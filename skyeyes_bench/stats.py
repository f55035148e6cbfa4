"""Honest statistics for results: clustered bootstrap over sequences and a Bayesian paired
comparison of two methods.

Frames within one sequence (a drive along a lane at one yaw) are strongly correlated, so the
resampling unit is the **sequence**: a bootstrap resample draws K sequence ids with replacement
from the K test sequences; a per-frame metric is the mean over all frames of the drawn sequences
(with multiplicity); a set metric (FID, KID, FVD, KVD) is recomputed from the features of the
drawn sequences. The same drawn ids are used for the submission side and the ground-truth side
(paired), and, in `compare`, for both methods.

Pure functions on arrays; no file I/O here. The Student-t model is in `bayes`; which metric is
better higher or lower, and which bootstrap a set metric uses, comes from `metricspec`.
"""

from __future__ import annotations

import math

import numpy as np

from .bayes import StudentTPosterior, hdi, student_t_posterior  # noqa: F401  (re-exported)
from .metricspec import FRAME_METRICS, METRICS, SET_METRICS, metric_def  # noqa: F401  (re-exported)

#: Metrics for which a lower value is better (everything else: higher is better).
LOWER_IS_BETTER = frozenset(n for n, m in METRICS.items() if not m.higher_is_better)


def higher_is_better(metric: str) -> bool:
    return metric not in LOWER_IS_BETTER


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


def frame_metric_samples(values: np.ndarray, clusters: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Mean of per-frame values over each resample's frames.

    Args:
        values: [N] per-frame values (may hold +inf, e.g. PSNR of an exact frame).
        clusters: [N] int, the sequence id (0..K-1) of each frame.
        counts: [R, K] how often each sequence is drawn.
    Returns:
        [R] resampled means; +inf where a drawn sequence holds an infinite value.
    """
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
    def from_features(cls, sub: np.ndarray, gt: np.ndarray, seq: np.ndarray, n_clusters: int) -> FrechetBootstrap:
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
    def from_features(cls, sub: np.ndarray, gt: np.ndarray, seq: np.ndarray, n_clusters: int) -> MMDBootstrap:
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


def set_metric_bootstrap(metric: str, sub: np.ndarray, gt: np.ndarray, seq: np.ndarray, n_clusters: int):
    """The resampled version of a set metric, as its `metricspec` entry names it.

    Args:
        metric: a set metric's name ("fid", "kid", ...).
        sub: [N, D] submission features; gt: [N, D] ground-truth features of the same frames / clips.
        seq: [N] sequence id (0..n_clusters-1) of each row.
    Returns:
        A callable for `set_metric_samples` (FrechetBootstrap, MMDBootstrap, ...).
    """
    from .registry import load_entry_point

    spec = metric_def(metric)
    assert spec.kind == "set" and spec.bootstrap, metric
    return load_entry_point(spec.bootstrap)(sub, gt, seq, n_clusters)


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
    """
    out = np.empty(counts.shape[0])
    by_cluster = getattr(fn, "by_cluster", False)
    for r, c in enumerate(counts):
        out[r] = fn(c, c) if by_cluster else fn(c[clusters1], c[clusters2])
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
    """Paired clustered bootstrap: percentile interval of the mean of per-sequence advantages
    d [K] (each sequence its own cluster); None when d holds NaN (no interval exists)."""
    k = len(d)
    counts = resample_counts(resample_indices(k, resamples, seed), k)
    samples = frame_metric_samples(d, np.arange(k), counts)
    return None if np.isnan(samples).any() else percentile_interval(samples, level)


def compare_per_sequence(a: np.ndarray, b: np.ndarray, metric: str, *, resamples: int, level: float,
                         seed: int, walkers: int, steps: int, burn: int) -> dict:
    """Paired comparison of per-sequence values a [K], b [K] of one metric (same sequence order).

    Returns a JSON-able dict: mean advantage of A (> 0: A better), its clustered-bootstrap
    interval, and the Student-t posterior summary (P(A better), 95% HDI of mu), or the reason
    the model was not fitted.
    """
    d = advantage(a, b, metric)
    k = len(d)
    out: dict = {"metric": metric, "higher_is_better": higher_is_better(metric), "sequences": k,
                 "advantage_mean": float(np.mean(d)) if not np.isnan(d).any() else math.nan}
    interval = advantage_interval(d, resamples=resamples, level=level, seed=seed)
    out["bootstrap_interval"] = list(interval) if interval is not None else None
    out["level"] = level
    bayes: dict = {"fitted": False}
    n_inf = int(np.isinf(d).sum())
    if n_inf:
        bayes["note"] = (f"{n_inf} sequence(s) have an infinite difference (one method reproduces every "
                         f"frame exactly, the other does not); a Student-t model of finite differences "
                         f"does not apply")
        bayes["p_a_better"] = 1.0 if (d > 0).all() else 0.0 if (d < 0).all() else None
    elif k == 1:
        bayes["note"] = "one sequence: the spread of differences cannot be estimated; no interval"
        bayes["p_a_better"] = None
    elif float(np.std(d)) <= 1e-12 * max(1.0, float(np.abs(d).max())):
        # Zero variance: every sequence differs by the same amount (identical methods: 0).
        # A Student-t posterior would collapse to a point (sigma -> 0); report that point.
        bayes.update(note="zero variance: every per-sequence difference is equal; the posterior is a "
                          "point mass at that value (no sampling)",
                     mu_mean=float(d[0]), hdi=[float(d[0])] * 2,
                     p_a_better=0.5 if d[0] == 0 else float(d[0] > 0))
    else:
        post = student_t_posterior(d, walkers=walkers, steps=steps, burn=burn, seed=seed)
        bayes.update(fitted=True, mu_mean=float(post.mu.mean()), hdi=list(hdi(post.mu, 0.95)),
                     p_a_better=float(np.mean(post.mu > 0)), sigma_mean=float(post.sigma.mean()),
                     nu_median=float(np.median(post.nu)), acceptance=post.acceptance,
                     autocorr_steps=post.autocorr, kept_steps=post.kept_steps, warnings=list(post.warnings))
    out["bayes"] = bayes
    return out


# --------------------------------------------------------------------------- comparing results


def _comparable(a: dict, b: dict) -> list[str]:
    """Why two results files cannot be compared (empty: they can)."""
    why = []
    pa, pb = a["protocol"], b["protocol"]
    if pa["ref"] != pb["ref"]:
        why.append(f"A was scored with protocol {pa['ref']}, B with {pb['ref']}: results of different "
                   f"protocols or protocol versions are not comparable")
    elif pa["sha256"] != pb["sha256"]:
        why.append(f"protocol {pa['ref']} differs between A and B (sha256 {pa['sha256'][:12]}... vs "
                   f"{pb['sha256'][:12]}...): the protocol file changed between the runs")
    for ex in sorted(set(a.get("extractors", {})) | set(b.get("extractors", {}))):
        ea, eb = a["extractors"].get(ex, {}), b["extractors"].get(ex, {})
        if ea.get("weights_sha256") != eb.get("weights_sha256") and "ok" == ea.get("status") == eb.get("status"):
            why.append(f"extractor {ex} used different weights (sha256 {str(ea.get('weights_sha256'))[:12]}... "
                       f"vs {str(eb.get('weights_sha256'))[:12]}...): features are not comparable")
    if a["sha256"]["ground_truth"] != b["sha256"]["ground_truth"] or \
            a["dataset"]["sequences"] != b["dataset"]["sequences"]:
        why.append(f"A and B were scored against different ground truth (dataset {a['dataset']['name']!r} "
                   f"vs {b['dataset']['name']!r}, or its frames changed)")
    return why


def compare_results(a: dict, b: dict, feats_a: dict | None = None, feats_b: dict | None = None,
                    *, emcee_steps: int | None = None) -> dict:
    """Paired comparison of two results of the same protocol and ground truth, metric by metric.

    Per-frame metrics (PSNR, SSIM, LPIPS): per-sequence advantage of A, its clustered bootstrap
    interval and the Student-t posterior (P(A better), 95% HDI). Set metrics (FID, KID, FVD, KVD)
    have no per-sequence values: they are compared by the paired bootstrap only (the same
    resampled sequences for A, B and the ground truth), which needs both features sidecars.

    Raises:
        UserError: the results are not comparable (the message says why).
    """
    from .errors import UserError
    from .protocol import load_protocol

    why = _comparable(a, b)
    if why:
        raise UserError("cannot compare: " + "; ".join(why))
    st = load_protocol(a["protocol"]["ref"]).statistics
    steps = emcee_steps or st.emcee_steps
    burn = min(st.emcee_burn, steps // 3) if emcee_steps else st.emcee_burn
    seq_ids = a["dataset"]["sequences"]
    k = len(seq_ids)
    out = {"protocol": a["protocol"]["ref"], "a": a["submission"].get("method"), "b": b["submission"].get("method"),
           "sequences": k, "sign": "advantage of A: A - B where higher is better, B - A where lower is better; "
           "> 0 means A is better", "metrics": {}}
    for name, ma in a["metrics"].items():
        mb = b["metrics"].get(name)
        if mb is None or ma["status"] != "ok" or mb["status"] != "ok":
            out["metrics"][name] = {"status": "skipped", "note": f"{name} unavailable in "
                                    f"{'A' if ma['status'] != 'ok' else 'B'}"}
            continue
        if ma["kind"] == "frame":
            va = np.array([a["sequences"][s][name] for s in seq_ids])
            vb = np.array([b["sequences"][s][name] for s in seq_ids])
            r = compare_per_sequence(va, vb, name, resamples=st.bootstrap_resamples, level=st.interval,
                                     seed=st.seed, walkers=st.emcee_walkers, steps=steps, burn=burn)
            r.update(status="ok", a=ma["value"], b=mb["value"])
            out["metrics"][name] = r
            continue
        ex = ma["extractor"]
        if feats_a is None or feats_b is None or ex not in feats_a or ex not in feats_b:
            out["metrics"][name] = {"status": "skipped", "a": ma["value"], "b": mb["value"],
                                    "note": "features sidecars missing: set metrics are compared by resampling "
                                            "features only"}
            continue
        fa, fb = feats_a[ex], feats_b[ex]
        counts = resample_counts(resample_indices(k, st.bootstrap_resamples, st.seed), k)
        fna = set_metric_bootstrap(name, fa["sub"], fa["gt"], fa["seq"], k)
        fnb = set_metric_bootstrap(name, fb["sub"], fb["gt"], fb["seq"], k)
        sa = set_metric_samples(fna, fa["seq"], fa["seq"], counts)
        sb = set_metric_samples(fnb, fb["seq"], fb["seq"], counts)
        d = advantage(sa, sb, name)
        d = d[np.isfinite(d)]
        lo, hi = percentile_interval(d, st.interval) if len(d) else (math.nan, math.nan)
        mean = advantage(np.array([ma["value"]]), np.array([mb["value"]]), name)[0]
        out["metrics"][name] = {"status": "ok", "metric": name, "higher_is_better": higher_is_better(name),
                                "a": ma["value"], "b": mb["value"], "advantage_mean": float(mean),
                                "bootstrap_interval": [lo, hi], "level": st.interval,
                                "p_a_better_bootstrap": float(np.mean(d > 0)) if len(d) else None,
                                "bayes": {"fitted": False, "note": "set metric: no per-sequence values; paired "
                                                                   "bootstrap only"}}
    return out
