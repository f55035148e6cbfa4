"""The functions the metric table (`metricspec.METRICS`) names: each metric's value from its
protocol settings.

Per-frame metrics: `f(preds, gts, settings) -> [B]`; set metrics: the point estimate
`f(xs, xg, settings, seed) -> float` on the features of all frames (or clips). `settings` is the
protocol's `MetricSpec` of that metric. The pure metric code itself lives in
`skyeyes_bench.metrics`; these adapters only pass the protocol's settings to it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

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


# --------------------------------------------------------------------------- per sequence (depth)


@dataclass(frozen=True)
class SequenceData:
    """One test sequence as the depth-based metrics see it (`metricspec.MetricDef.per_sequence`)."""

    preds: np.ndarray  # [T, H, W, 3] submitted frames in [0, 1], in sequence order
    gts: np.ndarray  # [T, H, W, 3] ground-truth frames
    depths: np.ndarray  # [T, H, W] ground-truth planar depth, metres (+inf sky)
    cameras: list  # T cameras.Camera
    seen: Callable[[float], np.ndarray]  # depth tolerance -> bool [T, H, W] seen masks (cached)


def _region(seq: SequenceData, name: str, tol: float) -> np.ndarray:
    """bool [T, H, W]: the seen pixels for `*_seen`, the others for `*_unseen`."""
    seen = seq.seen(tol)
    return seen if name.endswith("_seen") else ~seen


def regions(seq: SequenceData, specs: list) -> dict[str, tuple[np.ndarray, np.ndarray | None]]:
    """psnr_seen / _unseen, ssim_seen / _unseen (values [T], pixel counts [T]) and unseen_share
    (the share of each frame's pixels no aerial view sees, [T], unweighted)."""
    from .metrics import regions as R

    out: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
    ssim_maps: dict[tuple, np.ndarray] = {}  # one map per setting serves both regions
    for m in specs:
        if m.name == "unseen_share":
            out[m.name] = ((~seq.seen(m.depth_tolerance)).mean(axis=(1, 2)), None)
        elif m.name.startswith("psnr_"):
            out[m.name] = R.psnr(seq.preds, seq.gts, _region(seq, m.name, m.depth_tolerance))
        else:
            kw = {k: getattr(m, k) for k in ("window", "sigma", "k1", "k2") if getattr(m, k) is not None}
            key = tuple(sorted(kw.items()))
            if key not in ssim_maps:
                ssim_maps[key] = image.ssim_map(seq.preds, seq.gts, **kw).mean(axis=-1)  # [T, H - 2r, W - 2r]
            out[m.name] = R.map_mean(ssim_maps[key], _region(seq, m.name, m.depth_tolerance))
    return out


def lpips_regions(seq: SequenceData, specs: list) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """lpips_seen / _unseen: the LPIPS spatial map's mean over the region ([T] values, [T] counts);
    one map per backbone serves both regions."""
    from .metrics.regions import masked_mean

    maps: dict[str, np.ndarray] = {}
    out = {}
    for m in specs:
        net = _LPIPS_NET.get(m.extractor or "lpips-alex-v0.1", "alex")
        if net not in maps:
            maps[net] = image.lpips_map(seq.preds, seq.gts, net=net)  # [T, H, W]
        out[m.name] = masked_mean(maps[net], _region(seq, m.name, m.depth_tolerance))
    return out


def warp(seq: SequenceData, specs: list) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """warp (the submission) / warp_floor (the ground truth): frame t warped into frame t + 1 with
    the ground-truth depth and poses, mean |difference| over the valid pixels ([T] values, the
    last frame NaN; [T] valid pixel counts)."""
    from .metrics.geometry import warp_coords, warp_error

    n_frames = len(seq.cameras)
    coords: dict[float, list] = {}
    out = {}
    for m in specs:
        tol = m.depth_tolerance
        if tol not in coords:  # the geometry depends on the ground truth only: once per tolerance
            coords[tol] = [warp_coords(seq.depths[t + 1], seq.cameras[t + 1], seq.depths[t], seq.cameras[t], tol)
                           for t in range(n_frames - 1)]
        frames = seq.preds if m.name == "warp" else seq.gts
        values, counts = np.full(n_frames, np.nan), np.zeros(n_frames, np.int64)
        for t, (uv, valid) in enumerate(coords[tol]):
            values[t], counts[t] = warp_error(frames[t], frames[t + 1], uv, valid)
        out[m.name] = (values, counts)
    return out


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


def frechet_inf(xs: np.ndarray, xg: np.ndarray, settings, seed: int) -> float:
    """FID∞ / FVD∞ (Chong & Forsyth 2020; `frechet_inf`): the Fréchet distance of the paired rows
    xs [N, D], xg [N, D] extrapolated to 1 / N = 0 from random subsets of the protocol's
    `num_sizes` sizes from `min_fraction` N to N (`num_subsets` subsets a size, drawn with `seed`).
    NaN below 3 rows (no line to fit)."""
    from .frechet_inf import FrechetInfinity

    w = np.ones(len(xs))
    return FrechetInfinity.from_features(xs, xg, np.zeros(len(xs), np.int64), 1, settings, seed)(w, w)


def frechet_inf_centre(xs: np.ndarray, xg: np.ndarray, settings, seed: int) -> float:
    """The centre of FD∞'s interval: the mean of FD∞ over `frechet_inf.CENTRE_SEEDS` subset seeds
    (`seed`, the value's own, and the next ones), i.e. the value with its subset noise averaged
    out (`frechet_inf`, "Interval"). NaN below 3 rows."""
    from .frechet_inf import FrechetInfinity

    w = np.ones(len(xs))
    return FrechetInfinity.from_features(xs, xg, np.zeros(len(xs), np.int64), 1, settings, seed).centre(w)
