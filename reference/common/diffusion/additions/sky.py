"""The sky from one fit: after sampling, each frame's sky moves to one smooth function of the
view direction, fitted to the whole sequence's sky pixels, so it holds still from frame to frame.

Not in the paper. A direction at infinity looks the same from every pose; the generated skies are
washes that change from frame to frame, and the ghosts of buildings painted into them.

Assumption: the sky is a smooth function of the direction (a clear sky: a gradient and a glow).
Checked on every sequence: where the trimmed fit leaves the kept sky pixels further from it than
`max_rms` (RMS over RGB in [0, 1]), the sky has structure no smooth function follows (clouds),
and this step leaves the sequence's frames as they are.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from skyeyes_bench.cameras import Camera

from .frames import as_frames, blend, hwc
from .view import SequenceView

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SkyConfig:
    """mix: how far the sky's pixels move to the fit (0: off); degree: of the polynomial in the
    direction's components; trim: the share of the largest residuals left out of the refit;
    max_rms: the smooth-sky check (module docstring)."""

    mix: float = 0.0
    degree: int = 2
    trim: float = 0.2
    # NOTE: twice the largest residual the validation ground truth's clear skies leave (0.012 over
    # the 32 sequences of every other yaw of synthtown-v2-small-val; median 0.002).
    max_rms: float = 0.025

    def __post_init__(self):
        if not 0.0 <= self.mix <= 1.0 or self.degree < 0 or not 0 <= self.trim < 1 or self.max_rms <= 0:
            raise ValueError(f"sky: mix {self.mix} (0..1, 0: off), degree {self.degree} (>= 0), trim {self.trim} "
                             f"(0 <= trim < 1), max_rms {self.max_rms} (> 0)")


class SkyFromOneFit:
    """The sky from one fit as a step after sampling (`SkyConfig`); `None` from `make` when off."""

    name = "sky from one fit"
    assumption = "the sky is a smooth function of the view direction, a clear sky (checked: the fit's residual)"
    needs_gaussians = True

    def __init__(self, cfg: SkyConfig):
        self.cfg = cfg
        self.residuals: dict[str, float] = {}  # sequence id -> the fit's RMS residual

    @classmethod
    def make(cls, cfg: SkyConfig) -> "SkyFromOneFit | None":
        return cls(cfg) if cfg.mix > 0 else None

    def __call__(self, imgs: torch.Tensor, view: SequenceView) -> torch.Tensor:
        h, w = imgs.shape[-2:]
        out, rms = sky_fit(imgs, view.cameras(h, w), view.depths(h, w), mix=self.cfg.mix, degree=self.cfg.degree,
                           trim=self.cfg.trim)
        self.residuals[view.sequence.id] = rms
        if rms > self.cfg.max_rms:
            log.info("%s: sky from one fit steps aside: the sky lies %.3f from one smooth function of the direction "
                     "(at most %s)", view.sequence.id, rms, self.cfg.max_rms)
            return imgs
        return out


def sky_basis(d: np.ndarray, degree: int) -> np.ndarray:
    """Unit directions [M, 3] (world, z up) -> the monomials of their components up to `degree` [M, K]."""
    cols = [np.ones(len(d))]
    for total in range(1, degree + 1):
        for i in range(total + 1):
            for j in range(total - i + 1):
                k = total - i - j
                cols.append(d[:, 0] ** i * d[:, 1] ** j * d[:, 2] ** k)
    return np.stack(cols, 1)


def sky_fit(imgs: torch.Tensor, cameras: list[Camera], depths: list[np.ndarray], *, mix: float = 1.0,
            degree: int = 2, trim: float = 0.2, up: float = 0.0) -> tuple[torch.Tensor, float]:
    """A sequence's frames [N, 3, H, W] in [0, 1] -> (the same with the sky one smooth function of
    the direction for the whole sequence, the fit's RMS residual over the kept pixels). Where the
    prior sees nothing (depth +inf) above the horizon (world ray z > `up`), the colour moves `mix`
    of the way to a polynomial of degree `degree` in the ray's direction, least squares over every
    frame's sky pixels (refitted without the `trim` share of the largest residuals: the ghosts of
    buildings the generator paints); half of that on the sky's border pixels. No sky: the frames
    unchanged and a residual of 0."""
    if not 0 < mix <= 1 or degree < 0 or not 0 <= trim < 1:
        raise ValueError(f"sky_fit: mix {mix} (0 < mix <= 1), degree {degree} (>= 0), trim {trim} (0 <= trim < 1)")
    n, _, h, w = imgs.shape
    if not (n == len(cameras) == len(depths)):
        raise ValueError(f"sky_fit: {n} frames, {len(cameras)} cameras, {len(depths)} depths")
    x = hwc(imgs)
    dirs, masks = [], []
    for c, dep in zip(cameras, depths):
        _, d = c.rays()
        dirs.append(d)
        masks.append(np.isinf(np.asarray(dep).ravel()) & (d[:, 2] > up))
    if not np.stack(masks).any():
        return imgs.clone(), 0.0
    d_all = np.concatenate([d[m] for d, m in zip(dirs, masks)])
    y_all = np.concatenate([x[k].reshape(-1, 3)[m] for k, m in enumerate(masks)])
    step = max(1, len(d_all) // 200_000)
    a, y = sky_basis(d_all[::step], degree), y_all[::step]
    coef = np.linalg.lstsq(a, y, rcond=None)[0]
    r = np.linalg.norm(a @ coef - y, axis=1)
    keep = np.ones(len(r), dtype=bool)
    if trim:
        keep = r <= np.quantile(r, 1.0 - trim)
        coef = np.linalg.lstsq(a[keep], y[keep], rcond=None)[0]
        r = np.linalg.norm(a @ coef - y, axis=1)
    rms = float(np.sqrt(np.mean(r[keep] ** 2)))
    out = x.copy()
    for k in range(n):
        if masks[k].any():
            target = np.clip(sky_basis(dirs[k], degree) @ coef, 0, 1).reshape(h, w, 3)
            out[k] = blend(x[k], target, masks[k].reshape(h, w), mix)
    return as_frames(out, imgs), rms
