"""Baking a fitted field into dense grids over the scene box, and rendering ground views by
marching rays through them.

Why: the field costs a hash encoding and a density MLP per sample, and with `init=none` the
occupancy grid never prunes a ground ray (every cell stays occupied), so the field renders
~2-3k rays/s on one CPU thread and a `small` test split (8 lanes x 256 frames x 128^2 = 33.5M
rays) would take hours. Baked renderers evaluate the trained field once on a grid and render by
interpolating it: SNeRG (Hedman et al. 2021, "Baking Neural Radiance Fields for Real-Time View
Synthesis", arXiv:2103.14645: density, diffuse colour and a feature vector in a sparse voxel
grid), PlenOctrees (Yu et al. 2021, arXiv:2103.14024: density and SH coefficients in an
octree). Here the grid is dense (the box is small: ~2.5M vertices at 0.5 m) and holds density
and one colour per vertex, since the ground cameras all look along nearly horizontal rays.

Grid (`BakedField`): vertex (k, j, i) sits at box units (x, y, z) = -1 + 2 (i, j, k) /
(shape - 1), so the box's faces are vertices and box units are torch.nn.functional.grid_sample's
normalised coordinates (align_corners=True; grid_sample reads x along W, y along H, z along D,
hence the [Z, Y, X] layout). Colour is stored premultiplied by density (sigma * rgb) and
divided by the interpolated density at a sample: a vertex in empty space, whose colour means
nothing, then does not darken its occupied neighbours (density-weighted colour interpolation).

Colour is view dependent in the field; a bake keeps one colour per vertex, evaluated for
`view`:
- "camera": the direction from the nearest ground camera centre to the vertex, the ray that
  camera would cast through it (the default: the closest to what the field renderer computes
  for the frames it will render);
- "horizontal": the mean over 8 horizontal directions (yaw k * 45 deg), a view-independent
  ground colour;
- "aerial": the mean over 8 directions looking 45 deg down (the aerial views' pitch), the colour
  the training views actually saw.

Rendering (`render_baked_rays`): the field renderer's samples (`sample_intervals`, the box only,
no jitter), densities by trilinear lookup in blocks of samples with early ray termination at
transmittance 1e-4, the same weights (`render_weights`) and compositing, colours looked up only
where a weight exceeds `colour_eps`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from reference.common.nerf.render import SceneBox, render_weights, sample_intervals, to_unit

#: Rays stop where the transmittance falls below exp(-T_STOP) = 1e-4 (as the field renderer).
T_STOP = 9.21

VIEWS = ("camera", "horizontal", "aerial")


@dataclass
class BakedField:
    """A field evaluated on the vertices of a regular grid over `box`.

    Attributes:
        sigma: [1, 1, Z, Y, X] density (1/m) at the vertices.
        sigma_rgb: [1, 3, Z, Y, X] density times colour (rgb in [0, 1]).
        box: the scene box the grid spans (its faces are vertices).
        view: how the colour's view direction was chosen (`VIEWS`).
    """

    sigma: torch.Tensor
    sigma_rgb: torch.Tensor
    box: SceneBox
    view: str = "camera"

    def __post_init__(self):
        assert self.sigma.ndim == 5 and self.sigma.shape[:2] == (1, 1), self.sigma.shape
        assert self.sigma_rgb.shape == (1, 3, *self.sigma.shape[2:]), (self.sigma_rgb.shape, self.sigma.shape)

    @property
    def shape(self) -> tuple[int, int, int]:
        """Vertices per axis (Z, Y, X)."""
        return tuple(self.sigma.shape[2:])

    def lookup_sigma(self, y: torch.Tensor) -> torch.Tensor:
        """Trilinear density [N] at box units y [N, 3] (zero outside the box)."""
        return _lookup(self.sigma, y)[:, 0]

    def lookup_rgb(self, y: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
        """Colour [N, 3] at box units y [N, 3] whose interpolated density is sigma [N]."""
        return (_lookup(self.sigma_rgb, y) / sigma.clamp_min(1e-12)[:, None]).clamp(0, 1)

    def state_dict(self) -> dict:
        return {"sigma": self.sigma.cpu(), "sigma_rgb": self.sigma_rgb.cpu(), "view": self.view,
                "box": [np.asarray(self.box.lo).tolist(), np.asarray(self.box.hi).tolist()]}

    @classmethod
    def from_state_dict(cls, sd: dict, device: str | torch.device = "cpu") -> "BakedField":
        box = SceneBox(np.array(sd["box"][0]), np.array(sd["box"][1]))
        return cls(sd["sigma"].to(device), sd["sigma_rgb"].to(device), box, sd["view"])


def _lookup(vol: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """vol [1, C, Z, Y, X] at box units y [N, 3] -> [N, C]; zero outside [-1, 1]^3."""
    assert y.ndim == 2 and y.shape[1] == 3, y.shape
    out = F.grid_sample(vol, y.reshape(1, 1, 1, -1, 3).to(vol.dtype), mode="bilinear", padding_mode="zeros",
                        align_corners=True)  # [1, C, 1, 1, N]
    return out.reshape(vol.shape[1], -1).T


def grid_shape(box: SceneBox, voxel_m: float) -> tuple[int, int, int]:
    """Vertices per axis (Z, Y, X) of a grid with spacing at most `voxel_m` (m) over the box."""
    side = 2 * box.half.numpy()
    nx, ny, nz = (max(2, math.ceil(float(s) / voxel_m - 1e-9) + 1) for s in side)
    return nz, ny, nx


def view_directions(view: str, dtype=torch.float32) -> torch.Tensor:
    """The 8 unit directions [8, 3] averaged over by `view` ("horizontal" or "aerial"), on the CPU
    (the same numbers for every device; the caller moves them)."""
    yaw = torch.arange(8, dtype=torch.float64, device="cpu") * (math.pi / 4)
    pitch = {"horizontal": 0.0, "aerial": -math.pi / 4}[view]
    dirs = torch.stack([torch.cos(yaw) * math.cos(pitch), torch.sin(yaw) * math.cos(pitch),
                        torch.full_like(yaw, math.sin(pitch))], -1)
    return dirs.to(dtype)


@torch.no_grad()
def bake_field(field, box: SceneBox, *, voxel_m: float, view: str = "camera", centres: torch.Tensor | None = None,
         grid=None, chunk: int = 65536) -> BakedField:
    """Evaluate `field` (a `NeRFField`) on a grid of spacing <= voxel_m over the box.

    Args:
        field: density(u) -> (sigma, geo) and colour(geo, dirs) -> rgb on the unit cube.
        box: the scene box (the part of space the ground renders march through).
        voxel_m: the largest vertex spacing (m) along any axis.
        view: the colour's view direction (module docstring, `VIEWS`).
        centres: [C, 3] ground camera centres (world, m), for view="camera".
        grid: the field's `OccupancyGrid`, or None. Vertices in cells it marks empty get density
            0, as the field renderer skips samples there.
        chunk: vertices evaluated at once.
    """
    if view not in VIEWS:
        raise ValueError(f"bake view={view!r}: expected one of {VIEWS}")
    if view == "camera" and (centres is None or len(centres) == 0):
        raise ValueError("bake view='camera' needs the ground camera centres")
    dev = next(field.parameters()).device
    shape = grid_shape(box, voxel_m)
    axes = [torch.linspace(-1, 1, n, device=dev) for n in shape]  # z, y, x
    zz, yy, xx = torch.meshgrid(*axes, indexing="ij")
    ys = torch.stack([xx, yy, zz], -1).reshape(-1, 3)  # [V, 3] box units, vertex order z-major
    centre, half = box.centre.to(dev), box.half.to(dev)
    fixed = None if view == "camera" else view_directions(view).to(dev)
    sig_out = torch.empty(len(ys), device=dev)
    rgb_out = torch.empty(len(ys), 3, device=dev)
    for s in range(0, len(ys), chunk):
        y = ys[s:s + chunk]
        u = to_unit(y)
        sig, geo = field.density(u)
        if grid is not None:
            sig = torch.where(grid.query(u), sig, torch.zeros_like(sig))
        if fixed is None:
            x = centre + y * half  # world
            near = centres[torch.cdist(x, centres).argmin(1)]
            dirs = F.normalize(x - near, dim=-1, eps=1e-9)
            rgb = field.colour(geo, dirs)
        else:
            k = len(fixed)
            rgb = field.colour(geo.repeat(k, 1), fixed.repeat_interleave(len(y), 0)).reshape(k, len(y), 3).mean(0)
        sig_out[s:s + chunk] = sig
        rgb_out[s:s + chunk] = rgb
    sigma = sig_out.reshape(1, 1, *shape)
    sigma_rgb = (sig_out[:, None] * rgb_out).T.reshape(1, 3, *shape)
    return BakedField(sigma.contiguous(), sigma_rgb.contiguous(), box, view)


@torch.no_grad()
def render_baked_rays(baked: BakedField, o: torch.Tensor, d: torch.Tensor, *, n_samples: int, near: float,
                      colour_eps: float = 1e-4, block: int = 16) -> dict:
    """rgb [R, 3] over black, opacity acc [R], depth [R] (expected t, m) and the number of
    density lookups of rays from o [R, 3] along unit d [R, 3] through the baked box.

    The samples are the field renderer's with the far field off (`n_samples` uniform in the part
    of the ray inside the box, from `near` m), so a bake of a smooth field renders what
    `render_camera(..., far_field=False)` renders (tests/reference/common/nerf/test_nerf_bake.py).
    """
    assert o.shape == d.shape and o.ndim == 2 and o.shape[1] == 3, (o.shape, d.shape)
    R = len(o)
    t = sample_intervals(o, d, baked.box, n_inner=n_samples, n_outer=0, near=near, far=near)
    mids, deltas = (t[:, 1:] + t[:, :-1]) / 2, t[:, 1:] - t[:, :-1]  # [R, S]
    centre, half = baked.box.centre.to(o), baked.box.half.to(o)
    o_box, d_box = (o - centre) / half, d / half  # rays in box units: y = o_box + t d_box

    sigmas = torch.zeros(mids.shape, dtype=o.dtype, device=o.device)
    ys_all = torch.zeros(*mids.shape, 3, dtype=o.dtype, device=o.device)  # sample positions, box units
    tau = torch.zeros(R, dtype=o.dtype, device=o.device)
    live = (deltas > 0).any(1).nonzero()[:, 0]  # rays that miss the box look nothing up
    lookups = 0
    # 1. Densities in blocks of samples, only on rays with light left (early termination).
    for s0 in range(0, mids.shape[1], block):
        if len(live) == 0:
            break
        s1 = min(s0 + block, mids.shape[1])
        every = len(live) == R  # no ray stopped yet: slices instead of gathers (a foggy field)
        rows = slice(None) if every else live
        ys = o_box[rows, None] + d_box[rows, None] * mids[rows, s0:s1, None]  # [r, s, 3]
        sig = baked.lookup_sigma(ys.reshape(-1, 3)).reshape(len(live), s1 - s0)
        lookups += sig.numel()
        sigmas[rows, s0:s1] = sig
        ys_all[rows, s0:s1] = ys
        tau[rows] += (sig * deltas[rows, s0:s1]).sum(1)
        live = live[tau[live] < T_STOP]
    # 2. The field renderer's weights; colours only where a sample carries light.
    weights, _ = render_weights(sigmas, deltas)
    lit = weights > colour_eps
    n_lit = int(lit.sum())
    if n_lit > lit.numel() // 2:  # most samples carry light (fog): look up all, no gathers
        cols = baked.lookup_rgb(ys_all.reshape(-1, 3), sigmas.reshape(-1)).reshape(R, -1, 3)
        rgb = ((weights * lit)[..., None] * cols).sum(1)
    else:
        ray, smp = lit.nonzero(as_tuple=True)
        cols = baked.lookup_rgb(ys_all[ray, smp], sigmas[ray, smp])
        rgb = torch.zeros(R, 3, dtype=o.dtype, device=o.device).index_add(0, ray, weights[ray, smp, None] * cols)
    return {"rgb": rgb, "acc": weights.sum(1), "depth": (weights * mids).sum(1), "lookups": lookups,
            "coloured": n_lit}


@torch.no_grad()
def render_baked_camera(baked: BakedField, cam, *, n_samples: int, near: float, colour_eps: float = 1e-4,
                        chunk: int = 1 << 16) -> tuple[np.ndarray, np.ndarray]:
    """(rgb [H, W, 3] over black, opacity [H, W]) of a `skyeyes_bench.cameras.Camera`."""
    dev = baked.sigma.device
    o, d = cam.rays()
    o = torch.tensor(o, dtype=torch.float32, device=dev)
    d = torch.tensor(d, dtype=torch.float32, device=dev)
    rgbs, accs = [], []
    for oc, dc in zip(o.split(chunk), d.split(chunk)):
        out = render_baked_rays(baked, oc, dc, n_samples=n_samples, near=near, colour_eps=colour_eps)
        rgbs.append(out["rgb"])
        accs.append(out["acc"])
    rgb = torch.cat(rgbs).reshape(cam.height, cam.width, 3).clamp(0, 1)
    return rgb.cpu().numpy(), torch.cat(accs).reshape(cam.height, cam.width).clamp(0, 1).cpu().numpy()


__all__ = ["BakedField", "VIEWS", "bake_field", "grid_shape", "render_baked_camera", "render_baked_rays",
           "view_directions"]
