"""The functions the metric table (`metricspec.METRICS`) names: each metric's value from its
protocol settings.

Per-frame metrics: `f(preds, gts, settings) -> [B]`; set metrics: the point estimate
`f(xs, xg, settings, seed) -> float` on the features of all frames (or clips). `settings` is the
protocol's `MetricSpec` of that metric. The pure metric code itself lives in
`skyeyes_bench.metrics`; these adapters only pass the protocol's settings to it.
"""

from __future__ import annotations

import numpy as np

from .metrics import image, sets

_LPIPS_NET = {"lpips-alex-v0.1": "alex", "lpips-vgg-v0.1": "vgg"}


# --------------------------------------------------------------------------- per frame


def psnr(preds: np.ndarray, gts: np.ndarray, settings) -> np.ndarray:
    """PSNR per frame [B] of preds, gts [B, H, W, 3] in [0, 1]."""
    return image.psnr(preds, gts)


def ssim(preds: np.ndarray, gts: np.ndarray, settings) -> np.ndarray:
    """SSIM per frame [B] with the protocol's window, sigma, k1, k2 (the defaults where unset)."""
    kw = {k: getattr(settings, k) for k in ("window", "sigma", "k1", "k2") if getattr(settings, k) is not None}
    return image.ssim(preds, gts, **kw)


def lpips(preds: np.ndarray, gts: np.ndarray, settings) -> np.ndarray:
    """LPIPS per frame [B] with the protocol's backbone (AlexNet unless it names VGG)."""
    net = _LPIPS_NET.get(settings.extractor or "lpips-alex-v0.1", "alex")
    return image.lpips(preds, gts, net=net)


# --------------------------------------------------------------------------- over the set


def frechet(xs: np.ndarray, xg: np.ndarray, settings, seed: int) -> float:
    """FID / FVD: Fréchet distance of the float64 statistics of xs [N, D] and xg [M, D]."""
    assert xs.ndim == 2 and xg.ndim == 2 and xs.shape[1] == xg.shape[1], (xs.shape, xg.shape)
    a, b = sets.FeatureStats(xs.shape[1]), sets.FeatureStats(xs.shape[1])
    a.update(xs)
    b.update(xg)
    return sets.frechet_distance(a.mean(), a.cov(), b.mean(), b.cov())


def mmd(xs: np.ndarray, xg: np.ndarray, settings, seed: int) -> float:
    """KID / KVD: unbiased polynomial MMD^2 of xs [N, D] and xg [M, D], averaged over the
    protocol's random subsets (drawn with `seed`)."""
    return sets.kernel_mmd(xs, xg, subset_size=settings.subset_size, num_subsets=settings.num_subsets or 1,
                           seed=seed)
