"""The plane-sweep cost volume of `mvs` and its aggregation: colour NCC of a reference view
against a source warped to fronto-parallel depth planes, the best-k mean over sources, semi-global
aggregation (Hirschmueller 2008) and the winning depth with a parabolic sub-plane refinement.
See `mvs` for the pipeline and its sources; `MVSConfig` holds the settings of both. Tensors are float32 on the device of their inputs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from skyeyes_bench.cameras import Camera


@dataclass
class MVSConfig:
    """Plane-sweep stereo settings.

    Attributes:
        num_sources: source views per reference view.
        min_angle_deg, max_angle_deg: triangulation angles outside this band score low.
        planes: depth hypotheses per reference view (uniform in inverse depth).
        window: NCC window side (px, odd).
        best_k: per pixel, the mean of the best `best_k` source costs.
        min_texture: colour standard deviation (0..1 units) below which a window's NCC is
            undefined; such pixels take their cost from the aggregation only.
        sgm_p1, sgm_p2: SGM penalties for a one-plane and a larger jump (cost units, NCC cost
            is 1 - ncc in [0, 2]).
        sgm_paths: 0 (winner-take-all on the raw cost), 4 or 8 aggregation directions.
        max_cost: a pixel whose best raw cost is above this is dropped (no match anywhere).
        min_consistent: other views whose depth must agree for a pixel to be kept.
        reproj_px, depth_rel: consistency thresholds (COLMAP: 2 px / 1%; our pixels are 8x larger
            on the ground than COLMAP's usual, so depth_rel is looser).
    """

    num_sources: int = 6
    min_angle_deg: float = 8.0
    max_angle_deg: float = 35.0
    planes: int = 96
    window: int = 5
    best_k: int = 2
    min_texture: float = 0.01
    sgm_p1: float = 0.05
    sgm_p2: float = 0.4
    sgm_paths: int = 4
    max_cost: float = 0.8
    min_consistent: int = 2
    reproj_px: float = 1.5
    depth_rel: float = 0.02


def _box_mean(x: torch.Tensor, w: int) -> torch.Tensor:
    """Mean over a w x w window of x [..., H, W] (edges: the window's part inside the image)."""
    shape = x.shape
    y = F.avg_pool2d(x.reshape(-1, 1, *shape[-2:]), w, stride=1, padding=w // 2, count_include_pad=False)
    return y.reshape(shape)


def _rel_transform(ref: Camera, src: Camera, device) -> tuple[torch.Tensor, torch.Tensor]:
    """(A [3, 3], b [3]) with source-camera point = d * A @ [u, v, 1] + b for a reference pixel
    (u, v) at planar depth d, then projected with the source K."""
    Rr, tr = ref.c2w[:3, :3], ref.c2w[:3, 3]
    Rs, ts = src.c2w[:3, :3], src.c2w[:3, 3]
    A = src.K @ Rs.T @ Rr @ np.linalg.inv(ref.K)
    b = src.K @ Rs.T @ (tr - ts)
    return torch.tensor(A, dtype=torch.float32, device=device), torch.tensor(b, dtype=torch.float32, device=device)


def ncc_costs(ref_img: torch.Tensor, src_img: torch.Tensor, ref: Camera, src: Camera, depths: torch.Tensor,
              cfg: MVSConfig) -> torch.Tensor:
    """Cost volume [D, H, W] = 1 - NCC of the reference and the source warped at each depth.

    ref_img, src_img: [3, H, W] in [0, 1]. depths: [D] planar depths of the reference (m).
    Entries where the warped window leaves the source image or lies behind it are NaN.
    """
    _, h, w = ref_img.shape
    device = ref_img.device
    A, b = _rel_transform(ref, src, device)
    v, u = torch.meshgrid(torch.arange(h, device=device, dtype=torch.float32) + 0.5,
                          torch.arange(w, device=device, dtype=torch.float32) + 0.5, indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)], 0).reshape(3, -1)  # [3, HW]
    a = A @ pix  # [3, HW]
    p = depths[:, None, None] * a[None] + b[None, :, None]  # [D, 3, HW]
    z = p[:, 2]
    zs = torch.where(z > 1e-6, z, torch.ones_like(z))
    us, vs = p[:, 0] / zs, p[:, 1] / zs
    sw, sh = src.width, src.height
    inside = (z > 1e-6) & (us >= 0) & (us <= sw) & (vs >= 0) & (vs <= sh)
    grid = torch.stack([us / sw * 2 - 1, vs / sh * 2 - 1], -1).reshape(1, -1, w, 2)  # [1, D*H, W, 2]
    warped = F.grid_sample(src_img[None], grid, mode="bilinear", padding_mode="border", align_corners=False)
    warped = warped.reshape(3, len(depths), h, w).permute(1, 0, 2, 3)  # [D, 3, H, W]
    win = cfg.window
    mr = _box_mean(ref_img, win)
    vr = (_box_mean(ref_img * ref_img, win) - mr * mr).clamp_min(0)
    mj = _box_mean(warped, win)
    vj = (_box_mean(warped * warped, win) - mj * mj).clamp_min(0)
    cov = _box_mean(warped * ref_img[None], win) - mj * mr[None]
    # Colour NCC: covariances and variances summed over channels, then normalised.
    ncc = cov.sum(1) / torch.sqrt(vr.sum(0)[None] * vj.sum(1)).clamp_min(1e-12)
    cost = 1.0 - ncc.clamp(-1, 1)
    textured = (vr.sum(0) / 3) > cfg.min_texture ** 2
    valid = inside.reshape(len(depths), h, w) & textured[None] & ((vj.sum(1) / 3) > (cfg.min_texture / 2) ** 2)
    return torch.where(valid, cost, torch.full_like(cost, float("nan")))


def aggregate_sources(costs: torch.Tensor, best_k: int) -> torch.Tensor:
    """[S, D, H, W] -> [D, H, W]: mean of the best `best_k` finite costs per entry (NaN if none)."""
    filled = torch.where(torch.isnan(costs), torch.full_like(costs, float("inf")), costs)
    k = min(best_k, costs.shape[0])
    best = torch.topk(filled, k, dim=0, largest=False).values  # [k, D, H, W]
    finite = torch.isfinite(best)
    n = finite.sum(0)
    s = torch.where(finite, best, torch.zeros_like(best)).sum(0)
    return torch.where(n > 0, s / n.clamp_min(1), torch.full_like(s, float("nan")))


def _sgm_path(cost: torch.Tensor, p1: float, p2: float, dim: int, reverse: bool) -> torch.Tensor:
    """One SGM scan [D, H, W] along image axis `dim` (1 = down the rows, 2 = along the columns)."""
    c = cost.movedim(dim, 0)  # [L, D, X]
    if reverse:
        c = c.flip(0)
    out = torch.empty_like(c)
    prev = c[0]
    out[0] = prev
    for i in range(1, c.shape[0]):
        pmin = prev.min(0, keepdim=True).values
        up = F.pad(prev[1:], (0, 0, 0, 1), value=float("inf"))
        down = F.pad(prev[:-1], (0, 0, 1, 0), value=float("inf"))
        best = torch.minimum(torch.minimum(prev, torch.minimum(up, down) + p1), pmin + p2)
        prev = c[i] + best - pmin
        out[i] = prev
    if reverse:
        out = out.flip(0)
    return out.movedim(0, dim)


def sgm(cost: torch.Tensor, p1: float, p2: float, paths: int) -> torch.Tensor:
    """Semi-global aggregation [D, H, W] -> [D, H, W] over 4 (rows and columns, both ways) paths.

    NaN costs (no source saw the pixel at that depth) enter as the pixel's mean finite cost, so
    they neither attract nor repel the path.
    """
    if paths == 0:
        return cost
    if paths not in (4,):
        raise ValueError(f"sgm paths {paths}: expected 0 or 4")
    nanmask = torch.isnan(cost)
    fill = torch.nanmean(cost, dim=0, keepdim=True).nan_to_num(1.0)
    c = torch.where(nanmask, fill.expand_as(cost), cost)
    total = torch.zeros_like(c)
    for dim in (1, 2):
        for rev in (False, True):
            total += _sgm_path(c, p1, p2, dim, rev)
    return total / 4


def winner(cost: torch.Tensor, inv_depths: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Winner-take-all with parabolic sub-plane refinement in inverse depth.

    cost: [D, H, W]; inv_depths: [D] (uniformly spaced). Returns depth [H, W] (m) and the
    winning index [H, W].
    """
    d = cost.shape[0]
    idx = cost.argmin(0)  # [H, W]
    i0 = (idx - 1).clamp(0, d - 1)
    i2 = (idx + 1).clamp(0, d - 1)
    c0 = cost.gather(0, i0[None])[0]
    c1 = cost.gather(0, idx[None])[0]
    c2 = cost.gather(0, i2[None])[0]
    denom = c0 - 2 * c1 + c2
    interior = (idx > 0) & (idx < d - 1) & (denom > 1e-9)
    off = torch.where(interior, 0.5 * (c0 - c2) / denom.clamp_min(1e-9), torch.zeros_like(c1)).clamp(-0.5, 0.5)
    step = inv_depths[1] - inv_depths[0] if d > 1 else inv_depths.new_zeros(())
    inv = inv_depths[idx] + off * step
    return 1.0 / inv, idx
