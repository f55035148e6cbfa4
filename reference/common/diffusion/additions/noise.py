"""Carried noise: each frame's starting noise carried along the optical flow between the prior's
renders of consecutive frames, so that frames agree before the first denoising step.

Not in the paper: Skyeyes samples every frame from pure Gaussian noise (Fig. 2 caption). The
idea is Control-A-Video's motion-adaptive noise initializer (Chen et al. 2023), which the paper
cites (Sec. 2.3), and vid2vid-zero's; the split of a carried sample over the pixels it spreads to
is the discrete form of the noise transport of Chang et al. (ICLR 2024).

Assumption: the scene is still and the prior's renders move as the picture does, so the flow
between them is the camera's motion. Where it fails (the flow's forward-backward check, a
pixel new to the frame), a pixel keeps its own noise; every pixel stays exactly N(0, 1).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from .view import DIS_MIN_PX, SequenceView, flow_coords, grid_coords


@dataclass(frozen=True)
class CarriedNoiseConfig:
    """share: how much of frame j - 1's noise frame j carries (0: none, every frame its own draw,
    the paper's sampling; 1: all of it where the flow reaches)."""

    share: float = 0.0

    def __post_init__(self):
        if not 0.0 <= self.share <= 1.0:
            raise ValueError(f"noise.share {self.share}: expected 0 <= share <= 1 (0: off)")


class CarriedNoise:
    """The starting-noise addition (`CarriedNoiseConfig`); `None` from `make` when off."""

    name = "carried noise"
    assumption = "a still scene whose prior renders move as the picture does (their optical flow is the camera's motion)"
    needs_gaussians = False

    def __init__(self, cfg: CarriedNoiseConfig):
        self.cfg = cfg

    @classmethod
    def make(cls, cfg: CarriedNoiseConfig) -> "CarriedNoise | None":
        return cls(cfg) if cfg.share > 0 else None

    def __call__(self, own: torch.Tensor, view: SequenceView) -> torch.Tensor:
        """own [N, C, h, w] (every frame's own draw, `sample.frame_noise`) -> the carried noise."""
        h, w = own.shape[-2:]
        f = -(-DIS_MIN_PX // min(h, w))  # 1 on every preset's grid; more for grids DIS refuses
        return carried_noise(own, grid_coords(flow_coords(view.renders(h * f, w * f)), f), self.cfg.share)


def carried_noise(own: torch.Tensor, coords: Callable[[int], tuple[np.ndarray, np.ndarray]],
                  share: float) -> torch.Tensor:
    """Motion-aligned starting noise of a sequence: own [N, C, h, w], each frame's own standard
    normal draw, in sequence order -> [N, C, h, w], white like it: every pixel N(0, 1),
    independent of every other pixel of its frame.

    Frame 0 keeps its own. In frame j, the pixels the previous frame reaches (`coords(j)`:
    (uv, valid) on the h x w grid, `flow_coords` of the renders at that size) come in groups,
    the k pixels whose nearest source is one pixel x of frame j - 1's noise. A group's mean
    times sqrt(k) is sqrt(share) x plus sqrt(1 - share) of the same of its own draw, and what
    the group holds beyond its mean is its own draw's (own minus the group's mean of own): the
    carried sample is split among the pixels it spreads to as an exact conditional draw, where
    nearest-neighbour copies would repeat one sample over a zoomed region. k = 1 gives
    sqrt(share) x + sqrt(1 - share) own; elsewhere the pixel is its own."""
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"carried_noise: share {share}, expected 0 <= share <= 1")
    n, c, h, w = own.shape
    dev = own.device
    out = [own[0]] if n else []
    for j in range(1, n):
        uv, valid = coords(j)
        if uv.shape[:2] != (h, w):
            raise ValueError(f"carried_noise: coordinates of shape {uv.shape[:2]} for noise of {(h, w)}")
        ix = np.clip(np.floor(uv[..., 0]).astype(np.int64), 0, w - 1)
        iy = np.clip(np.floor(uv[..., 1]).astype(np.int64), 0, h - 1)
        tgt = torch.as_tensor(np.flatnonzero(valid), device=dev)
        src = torch.as_tensor((iy * w + ix).ravel(), device=dev)[tgt]
        e = own[j].reshape(c, h * w).double()
        k = torch.bincount(src, minlength=h * w).double()[src]  # each target's group size
        group_e = torch.zeros(c, h * w, dtype=torch.float64, device=dev).index_add_(1, src, e[:, tgt])[:, src]
        carried = out[-1].reshape(c, h * w).double()[:, src]
        mean = share ** 0.5 * carried + (1.0 - share) ** 0.5 * group_e / k.sqrt()  # N(0, 1): the group's sum / sqrt(k)
        z = e.clone()
        z[:, tgt] = mean / k.sqrt() + e[:, tgt] - group_e / k
        out.append(z.reshape(c, h, w).to(own.dtype))
    return torch.stack(out) if n else own.clone()
