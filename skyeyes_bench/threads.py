"""torch intra-op thread count, set in one place for the metrics and the reference methods."""

from __future__ import annotations

import os


def set_threads(n: int = 0) -> None:
    """Use `n` torch threads for the work that follows; with 0 every core we are given
    (OMP_NUM_THREADS wins when set, as in CI / scripts/test.sh).

    Callers set it at each stage, because a stage they run inside leaves its own setting behind
    (the Gaussian prior of Skyeyes runs on one thread; the UNet and the extractors want every core).
    """
    import torch

    n = n or int(os.environ.get("OMP_NUM_THREADS") or os.cpu_count() or 1)
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
