"""Coverage of FD∞'s 95% interval in the Gaussian simulation of the tests (issue 39), about its
centre (the value averaged over `frechet_inf.CENTRE_SEEDS` subset seeds, as `evaluate` makes it)
and, on the same replicates, about the value alone (before the centre).

    nice -n 19 .venv/bin/python bench/frechet_inf_coverage.py [--seeds 1,2] [--draws 32]

16-d Gaussians with a closed-form distance, N = 64, 256, 1024, 4096 rows in K = 16 clusters,
`--draws` data sets per N and seed, R = 80 half-samples, 6 sizes x 4 subsets
(`skyeyes_bench.synthetic.simulate`). Prints, per seed and pooled, the share of draws whose interval
holds the truth, per N and overall, and the load average (other processes slow this down, not
the figures). docs/metrics.md, "FID∞ and FVD∞", has the measured table.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from skyeyes_bench.synthetic import simulate


def _coverage(rows_by_n: dict, truth: float) -> tuple[dict, float]:
    each = {n: float(np.mean([lo <= truth <= hi for _, lo, hi in rows])) for n, rows in rows_by_n.items()}
    return each, float(np.mean([lo <= truth <= hi for rows in rows_by_n.values() for _, lo, hi in rows]))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="1,2", help="data seeds, comma-separated (default 1,2)")
    ap.add_argument("--draws", type=int, default=32, help="data sets per N and seed (default 32)")
    args = ap.parse_args(argv)
    pooled: dict[str, dict] = {"fid_inf": {}, "fid_inf_value": {}}
    truth = None
    for seed in (int(s) for s in args.seeds.split(",")):
        t0 = time.perf_counter()
        draws, truth = simulate(args.draws, seed)
        for key, label in (("fid_inf", "about the centre"), ("fid_inf_value", "about the value")):
            each, overall = _coverage(draws[key], truth)
            print(f"seed {seed} {label:17s} {overall:.3f}  per N {each}", flush=True)
            for n, rows in draws[key].items():
                pooled[key].setdefault(n, []).extend(rows)
        print(f"  ({time.perf_counter() - t0:.0f} s, load {os.getloadavg()[0]:.1f})", flush=True)
    for key, label in (("fid_inf", "about the centre"), ("fid_inf_value", "about the value")):
        each, overall = _coverage(pooled[key], truth)
        print(f"pooled {label:17s} {overall:.3f}  per N {each}")


if __name__ == "__main__":
    main()
