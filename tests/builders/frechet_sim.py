"""The Gaussian simulation of FD∞ (issue 39), shared by tests/skyeyes_bench/test_frechet_inf.py
and bench/frechet_inf_coverage.py (no tests here): `gaussians` and `simulate` live in
`skyeyes_bench.synthetic` (bench/ imports them from there); the bias of FD per N here."""

import numpy as np

from skyeyes_bench.synthetic import gaussians, simulate  # noqa: F401  (the tests import them from here)


def fd_bias_of(draws: dict, truth: float) -> dict:
    return {n: np.mean([r[0] for r in rows]) - truth for n, rows in draws["fid"].items()}
