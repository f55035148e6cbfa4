"""Slow dense reference: every Gaussian against every pixel, a literal front-to-back loop.

Plain autograd, no tiles; the test oracle for `raster.py` (forward and backward). Use only on
tiny images and a few hundred Gaussians.
"""

from __future__ import annotations

import torch

from .project import SUPPORT_SIGMA, project, resolve_degree, sh_colors
from .raster import ALPHA_MAX, ALPHA_MIN, T_MIN


def composite_dense(means2d, conics, opacities, colors, background, valid, depths, width, height):
    """Loop over Gaussians sorted by depth exactly like 3DGS's per-pixel loop.

    Args: means2d [N, 2], conics [N, 3], opacities [N], colors [N, C], background [C],
    valid [N] bool, depths [N]. Returns (out [H, W, C], alpha [H, W]).
    """
    dtype, dev = colors.dtype, colors.device
    ys, xs = torch.meshgrid(torch.arange(height, dtype=dtype, device=dev), torch.arange(width, dtype=dtype, device=dev),
                            indexing="ij")
    px, py = xs.reshape(-1) + 0.5, ys.reshape(-1) + 0.5
    T = torch.ones(px.shape[0], dtype=dtype, device=dev)
    done = torch.zeros(px.shape[0], dtype=torch.bool, device=dev)
    out = torch.zeros(px.shape[0], colors.shape[1], dtype=dtype, device=dev)
    alpha_max = torch.tensor(ALPHA_MAX, dtype=dtype, device=dev)
    order = [int(i) for i in torch.argsort(depths.detach(), stable=True) if valid[i]]
    for i in order:
        dx, dy = px - means2d[i, 0], py - means2d[i, 1]
        a, b, c = conics[i]
        q = a * dx * dx + 2 * b * dx * dy + c * dy * dy
        alpha = torch.minimum(opacities[i] * torch.exp(-0.5 * q), alpha_max)
        hit = (q <= SUPPORT_SIGMA ** 2) & (alpha >= ALPHA_MIN) & ~done
        test_T = T * (1 - alpha)
        stop = hit & (test_T < T_MIN)
        done = done | stop
        hit = hit & ~stop
        alpha = torch.where(hit, alpha, torch.zeros_like(alpha))
        out = out + (alpha * T)[:, None] * colors[i]
        T = T * (1 - alpha)
    out = out + T[:, None] * background
    return out.reshape(height, width, -1), (1 - T).reshape(height, width)


def rasterize_dense(means, quats, scales, opacities, sh, viewmat, K, width, height, *, background=None,
                    sh_degree=None, near=0.01, far=1e10):
    """Same contract as `render.rasterize` (rgb, depth, alpha), computed densely."""
    dtype = means.dtype
    deg = resolve_degree(sh, sh_degree)
    if background is None:
        background = torch.zeros(3, dtype=dtype, device=means.device)
    viewmat = viewmat.to(dtype)
    proj = project(means, quats, scales, viewmat, K, width, height, near=near, far=far)
    colors = sh_colors(sh, means, viewmat, deg)
    feats = torch.cat([colors, proj["depths"][:, None]], -1)
    bg = torch.cat([background.to(dtype), background.new_zeros(1)])
    out, alpha = composite_dense(proj["means2d"], proj["conics"], opacities, feats, bg, proj["valid"],
                                 proj["depths"], width, height)
    depth = out[..., 3] / alpha.clamp_min(1e-6) * (alpha > 0)
    return {"rgb": out[..., :3], "depth": depth, "alpha": alpha}
