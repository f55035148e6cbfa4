"""Rays through a bounded scene box and its contracted far field, and volume rendering.

Space: world points are first normalised by the scene box (`SceneBox`: the region the ground
cameras see, mapped to [-1, 1]^3 per axis), then the far field is contracted as in mip-NeRF 360
(Barron et al. 2022, eq. 10) with the L-inf norm (as nerfstudio does for hash grids, so the
contracted space is the cube [-2, 2]^3 a grid covers without waste):
contract(y) = y if |y|_inf <= 1 else (2 - 1 / |y|_inf) y / |y|_inf. Distant buildings and the
ground towards the horizon land in the shell 1 < |y|_inf < 2.

Samples along a ray: `n_inner` uniform in the part of the ray inside the box (stratified while
training) and `n_outer` uniform in disparity from where it leaves the box to `far` (mip-NeRF 360's
spacing of the far field), as intervals [t_i, t_i+1] with the sample at the middle.

Volume rendering (Max 1995; NeRF eq. 3): alpha_i = 1 - exp(-sigma_i delta_i), transmittance
T_i = exp(-sum_{j<i} sigma_j delta_j), weight_i = T_i alpha_i, computed from the optical depths so
that neither dense thin layers (1e4 / m over 1 mm) nor thin long ones (1e-6 / m over 1 km) lose
precision (expm1, an exclusive cumulative sum).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class SceneBox:
    """Axis-aligned box (world, m) that maps to [-1, 1]^3; lo, hi [3]. `centre` and `half` are
    CPU tensors (from the numpy corners); users move them to their data (`.to(x)`)."""

    lo: np.ndarray
    hi: np.ndarray

    @property
    def centre(self) -> torch.Tensor:
        return torch.tensor((np.asarray(self.lo) + np.asarray(self.hi)) / 2, dtype=torch.float32, device="cpu")

    @property
    def half(self) -> torch.Tensor:
        return torch.tensor((np.asarray(self.hi) - np.asarray(self.lo)) / 2, dtype=torch.float32, device="cpu")

    def normalise(self, x: torch.Tensor) -> torch.Tensor:  # [..., 3] world -> box units
        return (x - self.centre.to(x)) / self.half.to(x)


def contract(y: torch.Tensor) -> torch.Tensor:
    """Box units y [..., 3] -> contracted [..., 3] in [-2, 2]^3 (L-inf mip-NeRF 360 contraction)."""
    n = y.abs().amax(-1, keepdim=True)
    safe = n.clamp_min(1.0)  # the far branch only where n > 1, so no division by 0 anywhere
    return torch.where(n <= 1, y, (2 - 1 / safe) * y / safe)


def to_unit(y: torch.Tensor) -> torch.Tensor:
    """Box units [..., 3] -> the grid's unit cube [0, 1]^3 (contracted, then [-2, 2] -> [0, 1])."""
    return ((contract(y) + 2) / 4).clamp(0, 1)


def box_interval(o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry and exit t [R] of rays o + t d (box units, [R, 3]) through [-1, 1]^3 (slab test);
    t_exit < t_entry where a ray misses the box."""
    inv = 1.0 / torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
    t0, t1 = (-1 - o) * inv, (1 - o) * inv
    return torch.minimum(t0, t1).amax(-1), torch.maximum(t0, t1).amin(-1)


def sample_intervals(o: torch.Tensor, d: torch.Tensor, box: SceneBox, *, n_inner: int, n_outer: int, near: float,
                     far: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """Interval edges t [R, n_inner + n_outer + 1] (m along unit world directions d [R, 3] from
    origins o [R, 3]). A generator jitters the inner edges (stratified sampling); None: uniform."""
    assert o.shape == d.shape and o.shape[-1] == 3, (o.shape, d.shape)
    half = box.half.to(o)
    t_in, t_out = box_interval(box.normalise(o), d / half)
    hit = t_out > t_in.clamp_min(near)
    a = torch.where(hit, t_in.clamp_min(near), torch.full_like(t_in, near))
    b = torch.where(hit, t_out, a)  # a miss has an empty inner part
    u = torch.linspace(0, 1, n_inner + 1, device=o.device, dtype=o.dtype).expand(len(o), -1)
    if generator is not None and n_inner > 0:
        jitter = (torch.rand(len(o), n_inner + 1, generator=generator, device="cpu").to(o) - 0.5) / n_inner
        jitter[:, 0] = jitter[:, -1] = 0
        u = u + jitter
    inner = a[:, None] + (b - a)[:, None] * u  # [R, n_inner + 1]
    f = torch.maximum(torch.full_like(b, far), b * 2)
    s = torch.linspace(0, 1, n_outer + 1, device=o.device, dtype=o.dtype)[1:]
    outer = 1 / (1 / b[:, None] * (1 - s) + 1 / f[:, None] * s)  # uniform in disparity, [R, n_outer]
    return torch.cat([inner, outer], -1)


def render_weights(sigmas: torch.Tensor, deltas: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Weights [R, S] and the transmittance left after the last sample [R], from densities
    sigmas [R, S] (1/m, >= 0) over interval lengths deltas [R, S] (m). S may be 0 (empty rays:
    weights [R, 0], transmittance 1)."""
    assert sigmas.shape == deltas.shape and sigmas.ndim == 2, (sigmas.shape, deltas.shape)
    tau = sigmas * deltas  # optical depth of each interval
    alpha = -torch.expm1(-tau)
    acc_tau = torch.cumsum(tau, -1)
    trans = torch.exp(-(acc_tau - tau))  # exclusive: the light that reaches interval i
    left = torch.exp(-acc_tau[:, -1]) if tau.shape[1] else torch.ones(len(tau), dtype=tau.dtype, device=tau.device)
    return trans * alpha, left


def composite(weights: torch.Tensor, colours: torch.Tensor, background: torch.Tensor | None = None
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """rgb [R, 3] (over `background` [3] where given, else over black) and opacity [R] from
    weights [R, S] and colours [R, S, 3]."""
    rgb = (weights[..., None] * colours).sum(1)
    acc = weights.sum(1)
    if background is not None:
        rgb = rgb + (1 - acc)[:, None] * background
    return rgb, acc


def distortion_loss(weights: torch.Tensor) -> torch.Tensor:
    """mip-NeRF 360's distortion loss (Barron et al. 2022, eq. 15) per ray [R], from weights
    [R, S] of samples spaced evenly in s-space (index / S: our inner samples are uniform in the
    box, the outer ones uniform in disparity, as mip-NeRF 360's s):
    sum_ij w_i w_j |s_i - s_j| + 1/3 sum_i w_i^2 (s_i+1 - s_i). Small when a ray's weight sits in
    one short stretch (a surface), large for weight spread along it (fog, floaters). O(S) with
    exclusive cumulative sums: sum_ij w_i w_j |s_i - s_j| = 2 sum_i w_i (s_i W_<i - (w s)_<i)."""
    assert weights.ndim == 2, weights.shape
    S = weights.shape[1]
    s = (torch.arange(S, dtype=weights.dtype, device=weights.device) + 0.5) / max(S, 1)  # [S] midpoints
    w_before = torch.cumsum(weights, 1) - weights  # [R, S]
    ws_before = torch.cumsum(weights * s, 1) - weights * s
    inter = 2 * (weights * (s * w_before - ws_before)).sum(1)
    intra = (weights ** 2).sum(1) / (3 * max(S, 1))
    return inter + intra
