"""The Gaussian simulation of FD∞ (issue 39), shared by tests/skyeyes_bench/test_frechet_inf.py
and bench/frechet_inf_coverage.py (no tests here): two Gaussians with a closed-form Fréchet
distance, and repeated data sets scored exactly as `evaluate` scores them."""

import numpy as np
import scipy.linalg

from skyeyes_bench import estimators, stats
from skyeyes_bench.protocol import MetricSpec


def gaussians(d, seed):
    """Two Gaussians in d dimensions and their Fréchet distance in closed form (scipy's sqrtm on
    the exact covariances)."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(d, d)) / np.sqrt(d)
    b = rng.normal(size=(d, d)) / np.sqrt(d)
    s1 = a @ a.T + 0.1 * np.eye(d)
    s2 = 0.5 * s1 + 0.1 * b @ b.T  # close to s1, so the 1 / N bias is large beside the spread
    m1, m2 = np.zeros(d), 0.02 * rng.normal(size=d)
    r = scipy.linalg.sqrtm(s1).real
    cross = np.trace(scipy.linalg.sqrtm(r @ s2 @ r).real)  # tr (S1^1/2 S2 S1^1/2)^1/2
    truth = float((m1 - m2) @ (m1 - m2) + np.trace(s1) + np.trace(s2) - 2 * cross)
    return (m1, np.linalg.cholesky(s1)), (m2, np.linalg.cholesky(s2)), truth


def simulate(draws_per_n: int, seed: int) -> tuple[dict, float]:
    """16-d Gaussians, N = 64 ... 4096 rows in K = 16 clusters, `draws_per_n` data sets per N;
    values and intervals exactly as `evaluate` makes them (the estimator; half-sampling
    replicates of the metric table's bootstrap; FD∞'s interval about its centre,
    `MetricDef.centre`; `stats.interval_from_replicates`, clipped at 0; level 0.95), with R = 80
    replicates and 6 sizes x 4 subsets to keep it short. "fid_inf_value": FD∞'s interval from the
    same replicates reflected about the value instead (as before the centre).
    Returns ({"fid" | "fid_inf" | "fid_inf_value": {N: [(value, lo, hi)]}}, the true distance)."""
    (m1, l1), (m2, l2), truth = gaussians(16, seed=0)
    k, level = 16, 0.95
    spec = MetricSpec(name="fid_inf", num_sizes=6, min_fraction=0.5, num_subsets=4)
    counts = stats.replicate_counts(k, 80, 0)
    rng = np.random.default_rng(seed)
    draws = {"fid": {}, "fid_inf": {}, "fid_inf_value": {}}
    for n in (64, 256, 1024, 4096):
        clusters = np.repeat(np.arange(k), n // k)
        for _ in range(draws_per_n):
            x = m1 + rng.normal(size=(n, 16)) @ l1.T
            y = m2 + rng.normal(size=(n, 16)) @ l2.T
            for name, est in (("fid", estimators.frechet), ("fid_inf", estimators.frechet_inf)):
                value = est(x, y, spec, 0)
                fn = stats.set_metric_bootstrap(name, x, y, clusters, k, spec, 0)
                reps = stats.set_metric_samples(fn, clusters, clusters, counts)
                centres = {name: None}
                if name == "fid_inf":
                    centres = {"fid_inf": estimators.frechet_inf_centre(x, y, spec, 0), "fid_inf_value": None}
                for key, centre in centres.items():
                    lo, hi, _ = stats.interval_from_replicates(value, reps, level, k, centre)
                    draws[key].setdefault(n, []).append((value, max(lo, min(0.0, value)), hi))
    return draws, truth


def fd_bias_of(draws: dict, truth: float) -> dict:
    return {n: np.mean([r[0] for r in rows]) - truth for n, rows in draws["fid"].items()}
