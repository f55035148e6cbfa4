"""Set metrics on feature vectors: Frechet distance (FID/FVD), polynomial-kernel MMD (KID/KVD),
and mergeable float64 feature statistics for sharded evaluation."""

from __future__ import annotations

import base64
import json
import os
from pathlib import Path

import numpy as np

from ..inputfiles import read_json
from ..outputfiles import atomic_path


def _clip_spectrum(w: np.ndarray) -> np.ndarray:
    """Eigenvalues of a PSD matrix with rounding noise removed.

    Eigenvalues below d * eps * max|w| cannot be told from 0 (eigh's backward error), and their
    square roots (~1e-8 relative each) would add up to visible bias over many null directions
    (fewer samples than dimensions), so they are set to 0.
    """
    tol = w.shape[0] * np.finfo(np.float64).eps * max(float(np.abs(w).max(initial=0.0)), np.finfo(np.float64).tiny)
    return np.where(w > tol, w, 0.0)


def frechet_distance(mu1: np.ndarray, sigma1: np.ndarray, mu2: np.ndarray, sigma2: np.ndarray) -> float:
    """Frechet distance between N(mu1, sigma1) and N(mu2, sigma2), in float64.

    d = |mu1 - mu2|^2 + tr(S1) + tr(S2) - 2 tr((sqrt(S1) S2 sqrt(S1))^(1/2)).
    The last trace is the sum of the square roots of the eigenvalues of the *symmetric* PSD
    matrix sqrt(S1) S2 sqrt(S1) (same spectrum as S1 S2), computed on the range of S1 only
    (an r x r matrix, r = numerical rank of S1), so no complex numbers arise and
    rank-deficient covariances (fewer samples than dimensions) need no regularising epsilon,
    unlike the `scipy.linalg.sqrtm(S1 @ S2)` of pytorch-fid / clean-fid / StyleGAN-V, which
    agrees on well-conditioned inputs.

    A result below 0 can only be rounding (the exact value is >= 0); it is clamped to 0.0.

    Args:
        mu1: [D] mean. sigma1: [D, D] covariance. mu2: [D]. sigma2: [D, D].

    Returns:
        The distance (>= 0).
    """
    mu1, mu2 = np.asarray(mu1, np.float64), np.asarray(mu2, np.float64)
    s1, s2 = np.asarray(sigma1, np.float64), np.asarray(sigma2, np.float64)
    d = mu1.shape[0]
    assert mu1.shape == (d,) and mu2.shape == (d,), (mu1.shape, mu2.shape)
    assert s1.shape == (d, d) and s2.shape == (d, d), (s1.shape, s2.shape)
    if not (np.isfinite(mu1).all() and np.isfinite(mu2).all() and np.isfinite(s1).all() and np.isfinite(s2).all()):
        raise ValueError("frechet_distance: non-finite mean or covariance")
    # Pivoted Cholesky with rank detection (LAPACK dpstrf): S1 = A A^T, A = P L of shape [D, r].
    # S1 S2 (same spectrum as sqrt(S1) S2 sqrt(S1)) then shares its non-zero eigenvalues with
    # the symmetric r x r matrix A^T S2 A: eigenvalues only, no eigenvectors, and with fewer
    # samples than dimensions r << D, so it is cheap. Pivots below D * eps * max(diag S1) are
    # rank-deficiency (LAPACK's default tolerance).
    from scipy.linalg import lapack

    c, piv, rank, info = lapack.dpstrf(np.array((s1 + s1.T) * 0.5, order="F"), lower=1)
    if info < 0:
        raise ValueError(f"frechet_distance: dpstrf argument {-info} invalid")
    a = np.zeros((d, rank))
    a[piv - 1] = np.tril(c)[:, :rank]  # undo the pivoting: A = P L
    m = a.T @ ((s2 + s2.T) * 0.5) @ a  # [r, r]
    w = np.linalg.eigvalsh((m + m.T) * 0.5) if rank else np.zeros(0)
    tr_covmean = np.sqrt(_clip_spectrum(w)).sum() if w.size else 0.0
    diff = mu1 - mu2
    val = float(diff @ diff + np.trace(s1) + np.trace(s2) - 2.0 * tr_covmean)
    return max(val, 0.0)


def _poly_kernel(a: np.ndarray, b: np.ndarray, degree: int, gamma: float, coef0: float) -> np.ndarray:
    return (gamma * (a @ b.T) + coef0) ** degree


def _mmd2_unbiased(x: np.ndarray, y: np.ndarray, degree: int, gamma: float, coef0: float) -> float:
    n, m = len(x), len(y)
    kxx = _poly_kernel(x, x, degree, gamma, coef0)
    kyy = _poly_kernel(y, y, degree, gamma, coef0)
    kxy = _poly_kernel(x, y, degree, gamma, coef0)
    sxx = (kxx.sum() - np.trace(kxx)) / (n * (n - 1))
    syy = (kyy.sum() - np.trace(kyy)) / (m * (m - 1))
    return float(sxx + syy - 2.0 * kxy.mean())


def kernel_mmd(x: np.ndarray, y: np.ndarray, *, degree: int = 3, gamma: float | None = None,
               coef0: float = 1.0, subset_size: int | None = None, num_subsets: int = 1,
               seed: int = 0) -> float:
    """Unbiased MMD^2 with the polynomial kernel k(a, b) = (gamma a.b + coef0)^degree.

    KID (Binkowski et al. 2018) as clean-fid / torchmetrics compute it: `num_subsets` subsets
    of m = min(subset_size, len(x), len(y)) rows drawn without replacement from each set, the
    unbiased estimate averaged over subsets. With `subset_size=None` the whole sets are used
    once (and `num_subsets` is ignored). The estimate can be slightly negative.

    Args:
        x: [N, D] features. y: [M, D] features.
        gamma: None means 1 / D.
        seed: subset sampling seed (numpy default_rng).

    Returns:
        MMD^2 (float).
    """
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    assert x.ndim == 2 and y.ndim == 2 and x.shape[1] == y.shape[1], (x.shape, y.shape)
    if len(x) < 2 or len(y) < 2:
        raise ValueError(f"kernel_mmd: need at least 2 samples per set, got {len(x)} and {len(y)}")
    g = 1.0 / x.shape[1] if gamma is None else float(gamma)
    if subset_size is None:
        return _mmd2_unbiased(x, y, degree, g, coef0)
    m = min(int(subset_size), len(x), len(y))
    if m < 2:
        raise ValueError(f"kernel_mmd: subset_size {subset_size} < 2")
    rng = np.random.default_rng(seed)
    draws = [(rng.choice(len(x), m, replace=False), rng.choice(len(y), m, replace=False))
             for _ in range(int(num_subsets))]
    if max(len(x), len(y)) ** 2 <= _GRAM_LIMIT:
        # Kernel matrices over the whole sets once, then each subset is an index lookup
        # (O(n^2 d) once instead of O(m^2 d) per subset; same values up to rounding).
        kxx, kyy = _poly_kernel(x, x, degree, g, coef0), _poly_kernel(y, y, degree, g, coef0)
        kxy = _poly_kernel(x, y, degree, g, coef0)
        vals = []
        for ix, iy in draws:
            a, b = kxx[np.ix_(ix, ix)], kyy[np.ix_(iy, iy)]
            vals.append((a.sum() - np.trace(a)) / (m * (m - 1)) + (b.sum() - np.trace(b)) / (m * (m - 1))
                        - 2.0 * kxy[np.ix_(ix, iy)].mean())
    else:
        vals = [_mmd2_unbiased(x[ix], y[iy], degree, g, coef0) for ix, iy in draws]
    return float(np.mean(vals))


#: Largest n^2 for which kernel_mmd precomputes whole kernel matrices (3 x 8 bytes each).
_GRAM_LIMIT = 4000 * 4000


def _enc(a: np.ndarray) -> str:
    """float64 array -> base64 of its little-endian bytes (exact and JSON-safe)."""
    return base64.b64encode(np.ascontiguousarray(a, dtype="<f8").tobytes()).decode("ascii")


def _dec(s: str, shape: tuple[int, ...]) -> np.ndarray:
    return np.frombuffer(base64.b64decode(s), dtype="<f8").reshape(shape).astype(np.float64)


class FeatureStats:
    """Running float64 statistics of feature vectors: n, sum and sum of outer products.

    Sums merge exactly (two shards' sums added are the statistics of the union), which is what
    sharded evaluation and the per-sequence bootstrap rely on.
    """

    def __init__(self, dim: int):
        self.dim = int(dim)
        self.n = 0
        self.sum = np.zeros(self.dim, np.float64)
        self.outer = np.zeros((self.dim, self.dim), np.float64)

    def update(self, feats: np.ndarray) -> "FeatureStats":
        """Add a batch.  feats: [N, D]."""
        f = np.asarray(feats, np.float64)
        assert f.ndim == 2 and f.shape[1] == self.dim, (f.shape, self.dim)
        self.n += f.shape[0]
        self.sum += f.sum(axis=0)
        self.outer += f.T @ f
        return self

    def merge(self, other: "FeatureStats") -> "FeatureStats":
        """A new FeatureStats of the union of both sets."""
        assert other.dim == self.dim, (other.dim, self.dim)
        out = FeatureStats(self.dim)
        out.n = self.n + other.n
        out.sum = self.sum + other.sum
        out.outer = self.outer + other.outer
        return out

    def mean(self) -> np.ndarray:
        """[D] mean."""
        if self.n < 1:
            raise ValueError("FeatureStats.mean: no samples")
        return self.sum / self.n

    def cov(self, biased: bool = False) -> np.ndarray:
        """[D, D] covariance; unbiased (n - 1, as np.cov and the FID references) by default."""
        if self.n < (1 if biased else 2):
            raise ValueError(f"FeatureStats.cov: {self.n} samples are too few")
        mu = self.mean()
        c = self.outer - self.n * np.outer(mu, mu)
        c = (c + c.T) * 0.5
        return c / (self.n if biased else self.n - 1)

    def to_dict(self) -> dict:
        return {"format": "skyeyes-featurestats-1", "dim": self.dim, "n": self.n,
                "sum_f64le_b64": _enc(self.sum), "outer_f64le_b64": _enc(self.outer)}

    @classmethod
    def from_dict(cls, d: dict) -> "FeatureStats":
        if d.get("format") != "skyeyes-featurestats-1":
            raise ValueError(f"FeatureStats.from_dict: unknown format {d.get('format')!r}")
        s = cls(d["dim"])
        s.n = int(d["n"])
        s.sum = _dec(d["sum_f64le_b64"], (s.dim,))
        s.outer = _dec(d["outer_f64le_b64"], (s.dim, s.dim))
        return s

    def save(self, path: str | os.PathLike) -> None:
        """Atomic write: `.json` as to_dict(), anything else as a .npz."""
        path = Path(path)
        with atomic_path(path) as tmp:
            if path.suffix == ".json":
                tmp.write_text(json.dumps(self.to_dict()))
            else:
                with open(tmp, "wb") as f:
                    np.savez(f, dim=self.dim, n=self.n, sum=self.sum, outer=self.outer)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "FeatureStats":
        path = Path(path)
        if path.suffix == ".json":
            return cls.from_dict(read_json(path, allow_nan=True))
        with np.load(path, allow_pickle=False) as z:
            s = cls(int(z["dim"]))
            s.n = int(z["n"])
            s.sum = z["sum"].astype(np.float64)
            s.outer = z["outer"].astype(np.float64)
        return s
