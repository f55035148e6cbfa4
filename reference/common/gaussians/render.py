"""`rasterize`: the public splatting entry point (gsplat's parameterisation).

Dispatches to gsplat when the tensors live on CUDA and gsplat is importable (optional, never
required); otherwise runs the pure-PyTorch tile rasterizer of `raster.py`.
"""

from __future__ import annotations

import torch

from . import raster
from .project import project, resolve_degree, sh_colors


def rasterize(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
              sh: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int, *,
              background: torch.Tensor | None = None, sh_degree: int | None = None, near: float = 0.01,
              far: float = 1e10, tile: int = raster.TILE, backend: str = "auto") -> dict[str, torch.Tensor]:
    """Render 3D Gaussians from one camera.

    Args:
        means: [N, 3] world (m). quats: [N, 4] wxyz (any norm). scales: [N, 3] linear (m).
        opacities: [N] in [0, 1]. sh: [N, K, 3] SH coefficients, K = (d+1)^2, d <= 3.
        viewmat: [4, 4] world-to-camera (OpenCV). K: [3, 3] px. background: [3] (default black).
        sh_degree: degree to use (<= what sh holds; default all of it).
        backend: "auto" (gsplat on CUDA if installed), "torch" or "gsplat".
        tile: the torch rasterizer's tile side (px); gsplat uses its own default (16), the only
            tile size it tests (its `rasterization` docs).

    Returns dict: rgb [H, W, 3], depth [H, W] (expected planar depth of the composited
    Gaussians, m; 0 where alpha is 0), alpha [H, W], radii [N] px, means2d [N, 2] px (retains
    grad for densification; gsplat's is [1, N, 2], the tensor its graph uses), visible [N] bool.
    """
    n = means.shape[0]
    assert means.shape == (n, 3) and quats.shape == (n, 4) and scales.shape == (n, 3), (means.shape, quats.shape, scales.shape)
    assert opacities.shape == (n,) and sh.ndim == 3 and sh.shape[0] == n and sh.shape[2] == 3, (opacities.shape, sh.shape)
    deg = resolve_degree(sh, sh_degree)
    dtype = means.dtype
    if background is None:
        background = torch.zeros(3, dtype=dtype, device=means.device)
    background = background.to(means.device)  # no-op where the caller put it with the data
    if backend == "gsplat" or (backend == "auto" and means.is_cuda and _has_gsplat()):
        return _rasterize_gsplat(means, quats, scales, opacities, sh, viewmat, K, width, height,
                                 background, deg, near, far)
    viewmat = viewmat.to(dtype)
    proj = project(means, quats, scales, viewmat, K, width, height, near=near, far=far)
    means2d = proj["means2d"]
    if means2d.requires_grad:
        means2d.retain_grad()
    colors = sh_colors(sh, means, viewmat, deg)  # [N, 3]
    feats = torch.cat([colors, proj["depths"][:, None]], -1)  # depth rides along as a 4th channel
    bg = torch.cat([background.to(dtype), background.new_zeros(1)])
    ids, starts, tx, _ = raster.bin_tiles(means2d, proj["radii"], proj["depths"], proj["valid"], width, height, tile,
                                         conics=proj["conics"], opacities=opacities)
    out, alpha = raster.composite(means2d, proj["conics"], opacities, feats, bg, ids, starts, tx, width, height, tile,
                                  raster.BLOCK)
    depth = out[..., 3] / alpha.clamp_min(1e-6) * (alpha > 0)
    return {"rgb": out[..., :3], "depth": depth, "alpha": alpha, "radii": proj["radii"],
            "means2d": means2d, "visible": proj["valid"]}


def _has_gsplat() -> bool:
    try:
        import gsplat  # noqa: F401
    except Exception:
        return False
    return True


def _rasterize_gsplat(means, quats, scales, opacities, sh, viewmat, K, width, height, background, deg, near, far):
    """gsplat path (CUDA only). Untested on this CPU machine; kept to gsplat's documented API."""
    import gsplat

    rgbd, alphas, meta = gsplat.rasterization(
        means, quats, scales, opacities, sh, viewmat[None], K[None], width, height,
        near_plane=near, far_plane=far, sh_degree=deg,
        backgrounds=background[None], render_mode="RGB+ED", packed=False,
    )
    means2d = meta["means2d"]  # [1, N, 2]: a view of it would take no part in the graph, nor get a grad
    if means2d.requires_grad:
        means2d.retain_grad()  # densification reads its gradient, as on the torch path
    radii = meta["radii"][0]
    radii = radii.max(-1).values if radii.ndim == 2 else radii
    return {"rgb": rgbd[0, ..., :3], "depth": rgbd[0, ..., 3], "alpha": alphas[0, ..., 0],
            "radii": radii.to(means.dtype), "means2d": means2d, "visible": radii > 0}
