"""Coverage of set-metric (FID, KID) interval methods under clustered data, against a known
population value.

    nice -n 19 .venv/bin/python bench/coverage.py [--datasets 300] [--resamples 200] [--dim 16] [--frames 8]

Model (per simulated dataset): K clusters (scenes) of F frames. Ground-truth features
g = u_c + e_i with a scene effect u_c ~ N(0, tau^2 diag(lam)) and a frame term
e_i ~ N(0, sigma^2 diag(lam)); submission features s = a g + m + eta, eta ~ N(0, omega^2 I)
(so a submission frame is correlated with its own ground-truth frame, as in a real evaluation).
The marginal laws are Gaussian with diagonal covariances, so the population FID is the closed
form |m|^2 + sum_j (sqrt(v_j) - sqrt(a^2 v_j + omega^2))^2 with v = (tau^2 + sigma^2) lam; the
population MMD^2 of the KID kernel k(x, y) = (x.y / D + 1)^3 is E k(s, s') + E k(g, g') -
2 E k(s, g) over independent draws, each computed by conditioning on one argument (given x,
t = x.y / D + 1 is normal, E t^3 = mu^3 + 3 mu var) and averaging over 400k draws of the other.

Interval methods compared (all resample whole clusters; indices depend only on seed, R, K):
  percentile   cluster bootstrap with replacement, percentile interval (the old method)
  basic        the same replicates, basic (reflected) interval 2 est - [q_hi, q_lo]
  bca          the same replicates, bias-corrected and accelerated (cluster jackknife)
  half         subsampling K//2 clusters without replacement, rate/fpc-corrected:
               est - sqrt(m / (K - m)) (q - est)  (equals the delete-d jackknife scaling)
  sub-sqrt     subsampling m = K//2 without replacement, sqrt-n rate correction sqrt(m / K)
and, for each, "+est": the interval widened to contain its own point estimate when it does not.

Printed per configuration and method: coverage of the population value at 95%, how often the
interval contains its own estimate, mean width; and the load average (other processes slow
this down, not the figures).
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np

from skyeyes_bench import stats


def population_fid(m, lam_g, lam_s) -> float:
    return float(m @ m + np.sum((np.sqrt(lam_g) - np.sqrt(lam_s)) ** 2))


def _e_cubic(x, mu_y, var_y, d):
    """E_y (x.y / d + 1)^3 for each row of x [n, D], y ~ N(mu_y, diag(var_y))."""
    mu = x @ mu_y / d + 1.0
    var = (x**2) @ var_y / d**2
    return mu**3 + 3 * mu * var


def population_mmd(m, lam_g, lam_s, d, n=400_000, seed=123) -> float:
    rng = np.random.default_rng(seed)
    zero = np.zeros(d)
    acc = np.zeros(3)
    for _ in range(n // 50_000):
        xs = m + rng.standard_normal((50_000, d)) * np.sqrt(lam_s)
        xg = rng.standard_normal((50_000, d)) * np.sqrt(lam_g)
        acc += [_e_cubic(xs, m, lam_s, d).mean(), _e_cubic(xg, zero, lam_g, d).mean(),
                _e_cubic(xs, zero, lam_g, d).mean()]
    acc /= n // 50_000
    return float(acc[0] + acc[1] - 2 * acc[2])


def simulate(rng, k, f, d, lam, tau2, sigma2, a, m, omega2):
    c = np.repeat(np.arange(k), f)
    u = rng.standard_normal((k, d)) * np.sqrt(tau2 * lam)
    g = u[c] + rng.standard_normal((k * f, d)) * np.sqrt(sigma2 * lam)
    s = a * g + m + rng.standard_normal((k * f, d)) * math.sqrt(omega2)
    return s, g, c


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--datasets", type=int, default=300)
    ap.add_argument("--resamples", type=int, default=200)
    ap.add_argument("--dim", type=int, default=16)
    ap.add_argument("--frames", type=int, default=8, help="frames per cluster")
    ap.add_argument("--clusters", type=int, nargs="+", default=[8, 16])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    t0 = time.time()
    d = args.dim
    lam = 1.0 / (1.0 + np.arange(d) / 4.0)  # decaying spectrum, like real features
    tau2, sigma2, a, omega2 = 0.5, 0.5, 0.8, 0.3
    m = np.full(d, 0.5 / math.sqrt(d))
    lam_g = (tau2 + sigma2) * lam
    lam_s = a**2 * lam_g + omega2
    truth = {"fid": population_fid(m, lam_g, lam_s), "kid": population_mmd(m, lam_g, lam_s, d)}
    print(f"D={d}, {args.frames} frames per cluster, {args.datasets} datasets, {args.resamples} resamples; "
          f"population FID {truth['fid']:.4f}, KID {truth['kid']:.5f}")
    level = 0.95
    rng = np.random.default_rng(args.seed)
    for k in args.clusters:
        rec: dict = {}
        for _ in range(args.datasets):
            s, g, c = simulate(rng, k, args.frames, d, lam, tau2, sigma2, a, m, omega2)
            fns = {"fid": stats.FrechetBootstrap(s, g), "kid": stats.MMDBootstrap(s, g, c, c, k)}
            boot = stats.resample_counts(stats.resample_indices(k, args.resamples, args.seed), k)
            half = stats.subsample_counts(k, args.resamples, args.seed)
            jack = 1.0 - np.eye(k)
            for name, fn in fns.items():
                run = (lambda cc: stats.set_metric_samples(fn, c, c, cc))
                est = float(run(np.ones((1, k)))[0])
                rb, rh, rj = run(boot), run(half), run(jack)
                mh = k // 2
                ivs = {
                    "percentile": stats.percentile_interval(rb, level),
                    "basic": stats.basic_interval(est, rb, level),
                    "bca": stats.bca_interval(est, rb, rj, level),
                    "half": stats.subsample_interval(est, rh, level, math.sqrt(mh / (k - mh))),
                    "sub-sqrt": stats.subsample_interval(est, rh, level, math.sqrt(mh / k)),
                }
                for meth, (lo, hi) in list(ivs.items()):
                    if meth != "percentile":
                        ivs[meth + " +est"] = (min(lo, est), max(hi, est))
                for meth, (lo, hi) in ivs.items():
                    r = rec.setdefault((name, meth), [0, 0, 0.0, 0])
                    r[0] += lo <= truth[name] <= hi
                    r[1] += lo <= est <= hi
                    r[2] += hi - lo
                    r[3] += 1
                rec.setdefault((name, "estimate"), []).append(est)
        print(f"\nK={k} clusters x {args.frames} frames (N={k * args.frames})")
        for name in ("fid", "kid"):
            e = np.array(rec[(name, "estimate")])
            print(f"  {name}: mean estimate {e.mean():.4g} (population {truth[name]:.4g}, sd {e.std():.3g})")
            print(f"    {'method':<16}{'coverage':>9}{'has est':>9}{'width':>10}")
            for (n2, meth), r in rec.items():
                if n2 == name and meth != "estimate":
                    print(f"    {meth:<16}{r[0] / r[3]:>9.3f}{r[1] / r[3]:>9.3f}{r[2] / r[3]:>10.4g}")
    load = os.getloadavg()
    print(f"\n{time.time() - t0:.0f} s on {os.cpu_count()} cores; load average {load[0]:.2f} {load[1]:.2f} "
          f"{load[2]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
