"""The prior anchor: after sampling, each frame's coarse part (a Gaussian low-pass) moves part of
the way towards that of its own render of the 3D prior, whose colours are first mapped to the
sequence's frames; the detail stays the frame's own.

Not in the paper. The renders of a 3D prior hardly flicker (they are one model seen from moving
poses), so a frame's coarse part taken from its render is as steady as the prior, with no
correspondence between frames to get wrong.

Assumption: the prior's render is right about a frame's coarse layout, and its colours are the
frame's up to one affine map per cell of a grid of the screen, the same over the sequence (the
ACM corrects the prior's colours, not its layout). Where the prior is wrong about the layout (a
building it missed), the anchor pulls the frame's coarse part towards the prior's mistake.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .frames import blur_frames
from .view import SequenceView


@dataclass(frozen=True)
class PriorAnchorConfig:
    """mix: how far each frame's low-pass moves towards its render's (0: off); sigma_px: the
    low-pass's std in pixels of the model's resolution; tiles: the colour map's grid (tiles x tiles)."""

    mix: float = 0.0
    sigma_px: float = 3.0
    tiles: int = 4

    def __post_init__(self):
        if not 0.0 <= self.mix <= 1.0 or self.sigma_px <= 0 or self.tiles < 1:
            raise ValueError(f"anchor: mix {self.mix} (0..1, 0: off), sigma_px {self.sigma_px} (> 0), "
                             f"tiles {self.tiles} (>= 1)")


class PriorAnchor:
    """The prior anchor as a step after sampling (`PriorAnchorConfig`); `None` from `make` when off."""

    name = "prior anchor"
    assumption = "the prior's render is right about a frame's coarse layout and, up to one colour map per screen cell, its colours"
    needs_gaussians = False

    def __init__(self, cfg: PriorAnchorConfig):
        self.cfg = cfg

    @classmethod
    def make(cls, cfg: PriorAnchorConfig) -> "PriorAnchor | None":
        return cls(cfg) if cfg.mix > 0 else None

    def __call__(self, imgs: torch.Tensor, view: SequenceView) -> torch.Tensor:
        h, w = imgs.shape[-2:]
        renders = torch.as_tensor(view.renders(h, w), device=imgs.device).permute(0, 3, 1, 2)
        return prior_anchor(imgs, renders, self.cfg.sigma_px, self.cfg.mix, self.cfg.tiles)


def affine_colours(src: torch.Tensor, dst: torch.Tensor, tiles: int = 1) -> torch.Tensor:
    """src [N, 3, H, W] with its colours mapped by the affine map (a 3x3 matrix and an offset)
    that predicts dst [N, 3, H, W] best in least squares over all N frames. tiles > 1: one map
    for each cell of a tiles x tiles grid of the screen, fitted on the pixels of all N frames
    within a cell of it either way around the cell's centre, and the maps blended bilinearly
    between the cells' centres (constant beyond the outer ones), so the map varies smoothly over
    the screen and not at all in time."""
    n, _, h, w = src.shape
    cpu = torch.device("cpu")
    a = torch.cat([src.permute(0, 2, 3, 1).double().cpu(), torch.ones(n, h, w, 1, dtype=torch.float64, device=cpu)], -1)
    b = dst.permute(0, 2, 3, 1).double().cpu()
    cells = torch.arange(tiles, dtype=torch.float64, device=cpu) + 0.5
    cy, cx = cells * h / tiles, cells * w / tiles
    out = torch.zeros(n, h, w, 3, dtype=torch.float64, device=cpu)
    ys, xs = (torch.arange(k, dtype=torch.float64, device=cpu) + 0.5 for k in (h, w))
    wy = (1 - (ys[:, None] - cy[None]).abs() / (h / tiles)).clamp(min=0)  # [h, tiles] bilinear weights
    wx = (1 - (xs[:, None] - cx[None]).abs() / (w / tiles)).clamp(min=0)
    wy[ys < cy[0], 0], wy[ys > cy[-1], -1] = 1.0, 1.0  # constant beyond the outer centres
    wx[xs < cx[0], 0], wx[xs > cx[-1], -1] = 1.0, 1.0
    for i in range(tiles):
        rows = (ys - cy[i]).abs() < h / tiles
        for j in range(tiles):
            cols = (xs - cx[j]).abs() < w / tiles
            x, y = a[:, rows][:, :, cols].reshape(-1, 4), b[:, rows][:, :, cols].reshape(-1, 3)
            m = torch.linalg.lstsq(x, y).solution
            out += (wy[:, i, None] * wx[None, :, j])[None, :, :, None] * (a @ m)
    return out.to(src.dtype).permute(0, 3, 1, 2)


def anchored(x: torch.Tensor, target: torch.Tensor, sigma: float, mix: float = 1.0) -> torch.Tensor:
    """x [N, C, H, W] with its Gaussian low-pass (std `sigma` px, reflected at the border) moved
    `mix` of the way to `target`'s; the rest of x (its detail) stays its own."""
    x64 = x.detach().cpu().double()
    return (x64 + mix * torch.as_tensor(blur_frames(target, sigma) - blur_frames(x, sigma), device=x64.device)).to(x.dtype)


def prior_anchor(imgs: torch.Tensor, renders: torch.Tensor, sigma: float, mix: float = 1.0,
                 tiles: int = 1) -> torch.Tensor:
    """A sequence's decoded frames [N, 3, H, W] in [0, 1] -> the same anchored to the 3D prior:
    each frame's low-pass moves by `mix` towards its render's (`renders`, the same shape: what
    the ACM was conditioned on), whose colours are first mapped to the frames' by one affine fit
    over the sequence (`affine_colours`, on a `tiles` x `tiles` grid); clamped to [0, 1]."""
    if not 0 < mix <= 1 or sigma <= 0:
        raise ValueError(f"prior_anchor: sigma {sigma} (> 0), mix {mix} (0 < mix <= 1)")
    target = affine_colours(renders.float().cpu(), imgs.float().cpu(), tiles)
    return anchored(imgs.float().cpu(), target, sigma, mix).clamp(0.0, 1.0).to(imgs.device, imgs.dtype)
