"""Bayesian model of a paired comparison: the posterior of the location mu of per-cluster
differences (clusters: the protocol's scenes, or sequences for synthtown@1) under a Student-t
likelihood, sampled with emcee, and its highest-density interval.

What mu is: the centre of a heavy-tailed model of the per-cluster differences of per-cluster
frame means. It is the same quantity as `compare`'s headline advantage (difference of the
frame-weighted means) when every cluster has as many frames and the differences are symmetric;
otherwise it differs on purpose (one broken cluster does not move it), and `compare` says so
(`comparison.BAYES_ESTIMAND`). Callers give it at least `stats.MIN_CLUSTERS` differences.

Pure functions on arrays; `comparison.bayes_summary` is the caller.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def hdi(samples: np.ndarray, mass: float = 0.95) -> tuple[float, float]:
    """Shortest interval holding `mass` of the samples [S] (highest-density for unimodal)."""
    s = np.sort(np.asarray(samples, dtype=np.float64))
    n = len(s)
    k = max(1, int(math.ceil(mass * n)))
    if k >= n:
        return float(s[0]), float(s[-1])
    widths = s[k - 1:] - s[: n - k + 1]
    i = int(np.argmin(widths))
    return float(s[i]), float(s[i + k - 1])


@dataclass(frozen=True)
class StudentTPosterior:
    mu: np.ndarray  # [S] posterior samples of the location of the differences
    sigma: np.ndarray  # [S]
    nu: np.ndarray  # [S]
    acceptance: float  # mean acceptance fraction over walkers
    autocorr: float  # largest integrated autocorrelation time (steps) over parameters
    kept_steps: int  # steps per walker after burn-in
    warnings: tuple[str, ...]


# NOTE: priors after Kruschke (2013), "Bayesian estimation supersedes the t test" (BEST):
# mu ~ Normal(mean(d), (1000 sd(d))^2), sigma ~ Uniform(sd/1000, 1000 sd), nu - 1 ~ Exp(mean 29).
_NU_MEAN = 29.0


def _log_prob_factory(d: np.ndarray):
    from scipy.special import gammaln

    d = np.asarray(d, dtype=np.float64)
    m, s = float(d.mean()), float(d.std(ddof=1))
    lo, hi = math.log(s / 1000.0), math.log(s * 1000.0)
    prior_sd = 1000.0 * s

    def log_prob(theta: np.ndarray) -> np.ndarray:
        # theta: [W, 3] = (mu, log sigma, log(nu - 1)); vectorised over walkers
        mu, ls, lnu = theta[:, 0], theta[:, 1], theta[:, 2]
        ok = (ls > lo) & (ls < hi) & (lnu > -10) & (lnu < 10)
        sigma = np.exp(np.clip(ls, lo, hi))
        nu1 = np.exp(np.clip(lnu, -10, 10))
        nu = nu1 + 1.0
        lp = -0.5 * ((mu - m) / prior_sd) ** 2  # Normal prior on mu
        lp = lp + ls  # Uniform prior on sigma, expressed in log sigma (Jacobian sigma)
        lp = lp - nu1 / _NU_MEAN + lnu  # Exponential prior on nu - 1, in log(nu - 1)
        z = (d[None, :] - mu[:, None]) / sigma[:, None]
        ll = (gammaln((nu + 1) / 2) - gammaln(nu / 2) - 0.5 * np.log(nu * np.pi) - ls)[:, None] \
            - (nu[:, None] + 1) / 2 * np.log1p(z**2 / nu[:, None])
        out = lp + ll.sum(axis=1)
        return np.where(ok, out, -np.inf)

    return log_prob, m, s


def student_t_posterior(d: np.ndarray, *, walkers: int, steps: int, burn: int, seed: int) -> StudentTPosterior:
    """Sample the posterior of a Student-t model of per-cluster differences d [K] with emcee.

    Requires K >= 2 and sd(d) > 0 (callers handle the degenerate cases). Convergence is checked:
    mean acceptance fraction in (0.2, 0.8), kept chain longer than 50 autocorrelation times;
    otherwise a warning is recorded in `warnings` (the CLI prints it).
    """
    import emcee

    d = np.asarray(d, dtype=np.float64)
    assert d.ndim == 1 and len(d) >= 2
    log_prob, m, s = _log_prob_factory(d)
    assert s > 0
    rng = np.random.default_rng(seed)
    k = len(d)
    start = np.column_stack([
        m + s / math.sqrt(k) * rng.standard_normal(walkers),
        math.log(s) + 0.1 * rng.standard_normal(walkers),
        math.log(_NU_MEAN) + 0.1 * rng.standard_normal(walkers),
    ])
    # NOTE: differential-evolution moves (ter Braak 2006, as in emcee's docs) mix this 3-parameter
    # model about 3x faster than the default stretch move (autocorrelation ~12 vs ~35 steps).
    moves = [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]
    sampler = emcee.EnsembleSampler(walkers, 3, log_prob, vectorize=True, moves=moves)
    sampler.random_state = np.random.RandomState(seed).get_state()  # deterministic proposals
    sampler.run_mcmc(start, steps, progress=False)
    chain = sampler.get_chain(discard=burn, flat=True)
    acc = float(np.mean(sampler.acceptance_fraction))
    kept = steps - burn
    tau = sampler.get_autocorr_time(discard=burn, tol=0)
    tau_max = float(np.max(tau))
    notes = []
    if not 0.2 < acc < 0.8:
        notes.append(f"emcee acceptance fraction {acc:.2f} outside (0.2, 0.8)")
    if not np.isfinite(tau_max) or kept <= 50 * tau_max:
        notes.append(f"chain of {kept} steps is not > 50 autocorrelation times ({tau_max:.1f})")
    return StudentTPosterior(chain[:, 0], np.exp(chain[:, 1]), np.exp(chain[:, 2]) + 1.0,
                             acc, tau_max, kept, tuple(notes))
