"""FID∞ / FVD∞: the Fréchet distance extrapolated to infinitely many samples.

NOTE: Chong & Forsyth, "Effectively Unbiased FID and Inception Score and where to find them",
CVPR 2020 (arXiv:1911.07023), Sec. 3: the Fréchet distance of N samples, FD_N, is biased upward,
to first order by c / N with a c that depends on the generator, so two methods scored on the
same N can rank differently at another N, and scores on different N do not compare. Their
FID∞: FD_N on random subsets of 15 sizes spaced evenly from 5k to 50k, a least-squares line
of FD_N against 1 / N, and its value at 1 / N = 0. The code below is ours.

Two choices differ from their recipe (docs/metrics.md, "FID∞ and FVD∞", has the measurements):

* **Paired subsets.** Their reference statistics came from 50k training images, whose own
  1 / N bias was negligible; ours are the ground truth of the same frames (or clips), as few as
  the generated ones. A subset here takes the same rows of both sides (row i: one frame of the
  submission and the same frame of the ground truth), so the line extrapolates both sides to
  infinity. Subsets of the submission alone against all ground-truth rows leave about half the
  bias (the reference's part) in the intercept.
* **Smallest size N / 2** (protocol key `min_fraction`; theirs was 1 / 10). Our sets hold no more
  rows than feature dimensions (2048 frames in 2048-d, 128 clips in 400-d), where FD_N bends
  away from a line in 1 / N at small N; near N the line holds.

**Interval.** The value's random subsets add noise to it (subset noise) that its half-sampling
interval would carry twice: once in the value the replicates are reflected about, and again
through the value's part in that reflection, while the replicates' spread holds it once. In the
Gaussian simulation of tests/ (i.i.d. rows, 6 sizes x 4 subsets, 128 draws per seed) the
interval reflected about the value covered the truth in 0.93 and 0.88 of the draws, against a
stated 0.95. So the interval is reflected about `centre`, the mean of FD∞ over
`CENTRE_SEEDS` subset seeds (the value's own and the next ones): the same draws then covered
0.99 (a little wide: the replicates' own subset noise stays in their spread). The reported
value is the protocol's (one seed), and the interval is widened to contain it. Reflecting about
the replicates' mean instead covered as much but dropped the correction for the bias few scenes
leave in the value (docs/metrics.md).

Pure numpy on arrays, no file I/O. `FrechetInfinity` is both the metric table's bootstrap
(`stats.set_metric_bootstrap`: recomputed on each half-sample's rows) and, with every row
weighted once, the point estimate (`estimators.frechet_inf`).
"""

from __future__ import annotations

import math

import numpy as np

#: The recipe when a protocol leaves a setting out (the shipped protocols state all three).
DEFAULT_NUM_SIZES = 15  # Chong & Forsyth: 15 sizes
DEFAULT_MIN_FRACTION = 0.5
DEFAULT_NUM_SUBSETS = 1  # random subsets per size (Chong & Forsyth: 1)
#: Subset seeds averaged into the interval's centre (`FrechetInfinity.centre`). NOTE: the Gaussian
#: simulation's coverage (docs/metrics.md): 0.93 / 0.88 at 1 seed, 0.98 / ... at 4, 0.99 / ... at 16.
CENTRE_SEEDS = 16


def subset_sizes(n: int, num_sizes: int = DEFAULT_NUM_SIZES, min_fraction: float = DEFAULT_MIN_FRACTION) -> np.ndarray:
    """The subset sizes of `n` rows: `num_sizes` values spaced evenly from
    max(2, round(min_fraction n)) to n, rounded to integers (numpy's round: half to even),
    duplicates dropped. int64 [S], ascending; the last is n. Empty when n < 2."""
    assert num_sizes >= 2 and 0.0 < min_fraction < 1.0, (num_sizes, min_fraction)
    if n < 2:
        return np.zeros(0, np.int64)
    lo = max(2, int(round(min_fraction * n)))
    return np.unique(np.linspace(lo, n, num_sizes).round().astype(np.int64))


def extrapolate(sizes: np.ndarray, values: np.ndarray) -> float:
    """The intercept at 1 / N = 0 of the least-squares line of values [S] against 1 / sizes [S]
    (S >= 2 distinct sizes; NaN otherwise). Closed form on centred x: no ill-conditioned
    design matrix when 1 / N is small."""
    x = 1.0 / np.asarray(sizes, np.float64)
    y = np.asarray(values, np.float64)
    assert x.shape == y.shape and x.ndim == 1, (x.shape, y.shape)
    if len(np.unique(x)) < 2:
        return math.nan
    dx = x - x.mean()
    slope = float(dx @ (y - y.mean()) / (dx @ dx))
    return float(y.mean() - slope * x.mean())


def _setting(settings, key: str, default):
    value = None if settings is None else getattr(settings, key, None)
    return default if value is None else value


class FrechetInfinity:
    """FD∞ of paired feature rows under resampling weights.

    Each row i is one item (frame or clip): x1[i] the submission's features, x2[i] the ground
    truth's. For row weights w (a multiplicity per row; half-sampling: 0 or 1), the rows are
    listed with their multiplicities (M of them), and for each size n of `subset_sizes(M)` in
    ascending order `num_subsets` subsets are drawn: `rng.permutation(M)[:n]` with
    `rng = numpy.random.default_rng(seed)`, one stream per call, so a value depends only on the
    weights and the seed. FD_n of a size is the mean over its subsets of the Fréchet distance
    between the subset's submission rows and the same subset's ground-truth rows (`distance`:
    float64, unbiased covariances, exact). FD∞ = `extrapolate(sizes, FD_n)`.
    At the largest size the subset is every row, so FD_M is the plain FID / FVD.
    """

    def __init__(self, x1: np.ndarray, x2: np.ndarray, *, num_sizes: int = DEFAULT_NUM_SIZES,
                 min_fraction: float = DEFAULT_MIN_FRACTION, num_subsets: int = DEFAULT_NUM_SUBSETS, seed: int = 0):
        # x1: [N, D] submission features; x2: [N, D] ground truth, row i the same item as x1[i]
        from .stats import FrechetBootstrap

        self.x1, self.x2 = np.asarray(x1, np.float64), np.asarray(x2, np.float64)
        assert self.x1.ndim == 2 and self.x1.shape == self.x2.shape, (self.x1.shape, self.x2.shape)
        assert num_sizes >= 2 and 0.0 < min_fraction < 1.0 and num_subsets >= 1, (num_sizes, min_fraction, num_subsets)
        self.n = len(self.x1)
        self.num_sizes, self.min_fraction, self.num_subsets = int(num_sizes), float(min_fraction), int(num_subsets)
        self.seed = int(seed)
        # No more rows than dimensions (FID on SynthTown: 2048 frames in 2048-d): Gram matrices once, each
        # subset a lookup (FrechetBootstrap's route); else each subset's own covariances (D x D).
        self.gram = FrechetBootstrap(self.x1, self.x2) if self.n <= self.x1.shape[1] else None

    @classmethod
    def from_features(cls, sub: np.ndarray, gt: np.ndarray, seq: np.ndarray, n_clusters: int, settings=None,
                      seed: int = 0) -> FrechetInfinity:
        """The metric table's bootstrap factory (`stats.set_metric_bootstrap`): sub [N, D] and gt [N, D]
        rows of the same items; `settings` the protocol's `MetricSpec` (None: the defaults), `seed`
        its `[statistics] seed`."""
        return cls(sub, gt, num_sizes=_setting(settings, "num_sizes", DEFAULT_NUM_SIZES),
                   min_fraction=_setting(settings, "min_fraction", DEFAULT_MIN_FRACTION),
                   num_subsets=_setting(settings, "num_subsets", DEFAULT_NUM_SUBSETS), seed=seed)

    def curve(self, w: np.ndarray, seed: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The subset sizes, int64 [S], and FD_n at each, float64 [S], for row weights w [N], the
        subsets drawn with `seed` (None: this instance's)."""
        w = np.asarray(w, np.float64)
        assert w.shape == (self.n,) and (w >= 0).all() and (w == np.round(w)).all(), "integer row weights [N]"
        rows = np.repeat(np.arange(self.n), w.astype(np.int64))  # [M] each row as often as it is drawn
        m = len(rows)
        sizes = subset_sizes(m, self.num_sizes, self.min_fraction)
        rng = np.random.default_rng(self.seed if seed is None else seed)
        values = np.empty(len(sizes))
        for j, size in enumerate(sizes):
            if size == m:  # every row: one distance, whatever the number of subsets
                values[j] = self.distance(rows)
                continue
            values[j] = float(np.mean([self.distance(rows[rng.permutation(m)[:size]])
                                       for _ in range(self.num_subsets)]))
        return sizes, values

    def distance(self, rows: np.ndarray) -> float:
        """The Fréchet distance between the submission's rows `rows` (int [n], repeats allowed) and
        the ground truth's same rows: float64 means and unbiased covariances."""
        from .stats import frechet_eigh

        if self.gram is not None:
            c = np.bincount(rows, minlength=self.n).astype(np.float64)
            return self.gram(c, c)
        a, b = self.x1[rows], self.x2[rows]  # [n, D] each
        mu1, mu2 = a.mean(axis=0), b.mean(axis=0)
        a, b = a - mu1, b - mu2
        return frechet_eigh(mu1, a.T @ a / (len(rows) - 1), mu2, b.T @ b / (len(rows) - 1))

    def centre(self, w: np.ndarray, seeds: int = CENTRE_SEEDS) -> float:
        """The mean of FD∞ for row weights w [N] over `seeds` subset seeds: this instance's seed
        and the next `seeds - 1` (FD∞ is linear in FD_n, so this is FD∞ with `seeds` times the
        subsets a size); NaN below 3 rows."""
        return float(np.mean([self._extrapolated(w, self.seed + i) for i in range(seeds)]))

    def __call__(self, w1: np.ndarray, w2: np.ndarray) -> float:
        """FD∞ for row weights w1 = w2 [N] (paired rows: one weight per item); NaN when fewer
        than two distinct subset sizes exist (fewer than 3 rows)."""
        if not np.array_equal(np.asarray(w1), np.asarray(w2)):
            raise ValueError("FrechetInfinity: the rows are paired (submission and ground truth of one item), "
                             "so both sides take the same weights")
        return self._extrapolated(w1, self.seed)

    def _extrapolated(self, w: np.ndarray, seed: int) -> float:
        sizes, values = self.curve(w, seed)
        return extrapolate(sizes, values) if len(sizes) >= 2 else math.nan
