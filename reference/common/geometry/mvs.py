"""Dense multi-view stereo with known poses: plane sweep, cost aggregation, consistency, fusion.

The pipeline of the MVS row (Schoenberger et al. 2016, "Pixelwise View Selection for
Unstructured Multi-View Stereo", COLMAP), written as a plane sweep that runs on a CPU:

1. `select_sources`: for each reference view, the views that see the same ground with a usable
   triangulation angle (COLMAP picks sources by shared sparse points and angle; we have poses
   and the region, so we score the overlap of the region's floor and the angle directly).
2. `plane_sweep`: fronto-parallel depth hypotheses, uniform in inverse depth over the depth range
   of the region box; every source warped to the reference per hypothesis; colour normalised
   cross-correlation (NCC) over a square window; per pixel the mean of the best `best_k` source
   costs (occlusion-robust, as COLMAP's view selection approximates).
3. Semi-global aggregation (Hirschmueller 2008, as in OpenCV's StereoSGBM, applied to the
   plane-sweep volume): textureless road and roof pixels take the depth their neighbours agree
   on instead of a random winner. Winner-take-all with a parabolic sub-plane refinement.
4. `consistency_filter`: a depth survives if at least `min_consistent` other views' depth maps
   agree with it (forward-backward reprojection error and relative depth error), COLMAP's
   geometric-consistency fusion test.
5. `fuse`: surviving pixels lifted to world points with colour, normal (from the depth map) and
   footprint (the pixel's size on the surface, m), cropped to the region box (`cloud.PointCloud`).

The cost volume of steps 2 and 3 is computed in `sweep`, which also holds the settings
(`MVSConfig`); this module runs the pipeline.

All tensors are float32 on `device`; the same code runs on CUDA.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from skyeyes_bench.cameras import Camera

from .cloud import PointCloud
from .sweep import MVSConfig, aggregate_sources, ncc_costs, sgm, winner  # noqa: F401  (MVSConfig: callers read it here)


# --------------------------------------------------------------------------- view selection


def _box_floor_points(box: np.ndarray, step: float) -> np.ndarray:
    """[M, 3] grid on the box's floor plane z = max(box z min, 0)."""
    xs = np.arange(box[0, 0], box[1, 0] + 1e-9, step)
    ys = np.arange(box[0, 1], box[1, 1] + 1e-9, step)
    gx, gy = np.meshgrid(xs, ys)
    z = max(float(box[0, 2]), 0.0)
    return np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], 1)


def _visible(cam: Camera, pts: np.ndarray) -> np.ndarray:
    uv, z = cam.project(pts)
    with np.errstate(invalid="ignore"):
        return (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)


def select_sources(cams: list[Camera], box: np.ndarray, cfg: MVSConfig) -> list[list[int]]:
    """For each view, the indices of its `num_sources` best source views (maybe fewer, maybe none).

    Score of source s for reference r: number of region-floor points both see, times a weight of
    the median triangulation angle (1 inside [min_angle, max_angle], falling off outside, 0 for a
    shared centre: pure rotation gives no depth).
    """
    pts = _box_floor_points(box, max(2.0, float(np.ptp(box[:, :2], axis=0).max()) / 40))
    vis = np.stack([_visible(c, pts) for c in cams])  # [V, M]
    centres = np.stack([c.center for c in cams])
    out = []
    for r in range(len(cams)):
        scores = []
        for s in range(len(cams)):
            both = vis[r] & vis[s]
            if s == r or both.sum() < 8 or np.linalg.norm(centres[r] - centres[s]) < 1e-3:
                scores.append(0.0)
                continue
            p = pts[both]
            a = p - centres[r]
            b = p - centres[s]
            cosang = (a * b).sum(1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
            ang = float(np.degrees(np.median(np.arccos(np.clip(cosang, -1, 1)))))
            if ang < cfg.min_angle_deg:
                w = ang / cfg.min_angle_deg
            elif ang > cfg.max_angle_deg:
                w = max(0.0, 1.0 - (ang - cfg.max_angle_deg) / cfg.max_angle_deg)
            else:
                w = 1.0
            scores.append(float(both.sum()) * w)
        order = np.argsort(scores)[::-1]
        out.append([int(s) for s in order[:cfg.num_sources] if scores[s] > 0])
    return out


def depth_range(cam: Camera, box: np.ndarray, *, min_depth: float = 1.0, samples: int = 24) -> tuple[float, float] | None:
    """Planar depth range [near, far] (m) of the part of the region box inside `cam`'s frustum,
    or None when the camera sees none of it. A grid of `samples`^3 points fills the box."""
    axes = [np.linspace(box[0, i], box[1, i], samples) for i in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    vis = _visible(cam, pts)
    if not vis.any():
        return None
    _, z = cam.project(pts[vis])
    near = max(float(z.min()), min_depth)
    far = max(float(z.max()), near * 1.05)
    return near, far


# --------------------------------------------------------------------------- plane sweep


def plane_sweep(images: list[torch.Tensor], cams: list[Camera], ref: int, sources: list[int], box: np.ndarray,
                cfg: MVSConfig) -> torch.Tensor:
    """Depth map [H, W] (m; NaN where no depth was found) of view `ref` from its `sources`.

    images: [3, H, W] each, in [0, 1], on the device the sweep runs on.
    """
    img = images[ref]
    device = img.device
    h, w = img.shape[1:]
    if not sources:
        return torch.full((h, w), float("nan"), device=device)
    rng = depth_range(cams[ref], box)
    if rng is None:
        return torch.full((h, w), float("nan"), device=device)
    near, far = rng
    inv = torch.linspace(1.0 / near, 1.0 / far, cfg.planes, device=device)
    depths = 1.0 / inv
    costs = torch.stack([ncc_costs(img, images[s], cams[ref], cams[s], depths, cfg) for s in sources])
    raw = aggregate_sources(costs, cfg.best_k)  # [D, H, W]
    agg = sgm(raw, cfg.sgm_p1, cfg.sgm_p2, cfg.sgm_paths)
    depth, idx = winner(agg, inv)
    raw_best = raw.gather(0, idx[None])[0]
    ok = torch.isfinite(depth) & ~(raw_best > cfg.max_cost)  # NaN raw cost (textureless) is kept: SGM chose it
    ok &= ~torch.isnan(raw).all(0)  # no source saw the pixel at any depth
    return torch.where(ok, depth, torch.full_like(depth, float("nan")))


# --------------------------------------------------------------------------- consistency and fusion


def _unproject_map(cam: Camera, depth: torch.Tensor) -> torch.Tensor:
    """World points [H, W, 3] of a planar depth map [H, W]."""
    h, w = depth.shape
    device = depth.device
    v, u = torch.meshgrid(torch.arange(h, device=device, dtype=torch.float32) + 0.5,
                          torch.arange(w, device=device, dtype=torch.float32) + 0.5, indexing="ij")
    Kinv = torch.tensor(np.linalg.inv(cam.K), dtype=torch.float32, device=device)
    R = torch.tensor(cam.c2w[:3, :3], dtype=torch.float32, device=device)
    t = torch.tensor(cam.c2w[:3, 3], dtype=torch.float32, device=device)
    rays = torch.stack([u, v, torch.ones_like(u)], -1) @ Kinv.T  # [H, W, 3], z = 1
    return (rays * depth[..., None]) @ R.T + t


def _project_pts(cam: Camera, pts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World points [..., 3] -> pixel uv [..., 2] and planar depth [...] (uv NaN behind)."""
    device = pts.device
    R = torch.tensor(cam.c2w[:3, :3], dtype=torch.float32, device=device)
    t = torch.tensor(cam.c2w[:3, 3], dtype=torch.float32, device=device)
    K = torch.tensor(cam.K, dtype=torch.float32, device=device)
    pc = (pts - t) @ R
    z = pc[..., 2]
    zs = torch.where(z > 1e-6, z, torch.full_like(z, float("nan")))
    uv = (pc[..., :2] / zs[..., None]) * torch.stack([K[0, 0], K[1, 1]]) + torch.stack([K[0, 2], K[1, 2]])
    return uv, z


def consistency_filter(depths: list[torch.Tensor], cams: list[Camera], neighbours: list[list[int]],
                       cfg: MVSConfig) -> list[torch.Tensor]:
    """Keep a pixel's depth only where >= `min_consistent` neighbour depth maps agree with it.

    Agreement with view j (COLMAP's geometric consistency): the reference point X projects into
    j at uv_j with depth z; j's depth d_j at uv_j (nearest pixel) lifts back to X_j, which must
    reproject within `reproj_px` of the reference pixel, and |z - d_j| <= depth_rel * d_j.
    Returns the filtered maps (NaN where dropped).
    """
    out = []
    for r, (dr, cam) in enumerate(zip(depths, cams)):
        h, w = dr.shape
        device = dr.device
        pts = _unproject_map(cam, torch.nan_to_num(dr, nan=1.0))  # [H, W, 3]
        count = torch.zeros(h, w, dtype=torch.int32, device=device)
        v, u = torch.meshgrid(torch.arange(h, device=device, dtype=torch.float32) + 0.5,
                              torch.arange(w, device=device, dtype=torch.float32) + 0.5, indexing="ij")
        for j in neighbours[r]:
            cj, dj_map = cams[j], depths[j]
            uv, z = _project_pts(cj, pts)
            uvf = torch.nan_to_num(uv, nan=-1.0)
            iu = uvf[..., 0].floor().long()
            iv = uvf[..., 1].floor().long()
            inside = (iu >= 0) & (iu < cj.width) & (iv >= 0) & (iv < cj.height) & (z > 0)
            dj = dj_map[iv.clamp(0, cj.height - 1), iu.clamp(0, cj.width - 1)]
            ok = inside & torch.isfinite(dj)
            # Back-projection of j's depth at that pixel, into the reference.
            kj_inv = torch.tensor(np.linalg.inv(cj.K), dtype=torch.float32, device=device)
            Rj = torch.tensor(cj.c2w[:3, :3], dtype=torch.float32, device=device)
            tj = torch.tensor(cj.c2w[:3, 3], dtype=torch.float32, device=device)
            pix = torch.stack([iu.float() + 0.5, iv.float() + 0.5, torch.ones_like(z)], -1)
            xj = ((pix @ kj_inv.T) * torch.nan_to_num(dj, nan=1.0)[..., None]) @ Rj.T + tj
            uv_back, _ = _project_pts(cam, xj)
            err = torch.sqrt((uv_back[..., 0] - u) ** 2 + (uv_back[..., 1] - v) ** 2)
            ok &= (err <= cfg.reproj_px) & ((z - dj).abs() <= cfg.depth_rel * dj)
            count += ok.int()
        keep = torch.isfinite(dr) & (count >= cfg.min_consistent)
        out.append(torch.where(keep, dr, torch.full_like(dr, float("nan"))))
    return out


def depth_normals(cam: Camera, depth: torch.Tensor) -> torch.Tensor:
    """Unit world normals [H, W, 3] of a depth map (central differences; NaN where undefined),
    oriented towards the camera."""
    pts = _unproject_map(cam, depth)
    pad = F.pad(pts.permute(2, 0, 1)[None], (1, 1, 1, 1), mode="replicate")[0].permute(1, 2, 0)
    dx = pad[1:-1, 2:] - pad[1:-1, :-2]
    dy = pad[2:, 1:-1] - pad[:-2, 1:-1]
    n = torch.cross(dx, dy, dim=-1)
    n = n / n.norm(dim=-1, keepdim=True)
    towards = torch.tensor(cam.c2w[:3, 3], dtype=torch.float32, device=depth.device) - pts
    flip = (n * towards).sum(-1, keepdim=True) < 0
    return torch.where(flip, -n, n)


def fuse(depths: list[torch.Tensor], images: list[torch.Tensor], cams: list[Camera], box: np.ndarray, *,
         max_stretch: float = 4.0) -> PointCloud:
    """Lift every finite depth pixel to a world point inside `box` [2, 3] (PointCloud)."""
    parts = []
    for d, img, cam in zip(depths, images, cams):
        ok = torch.isfinite(d)
        if not ok.any():
            continue
        pts = _unproject_map(cam, torch.nan_to_num(d, nan=1.0))
        nrm = torch.nan_to_num(depth_normals(cam, torch.nan_to_num(d, nan=1.0)), nan=0.0)
        # Footprint: one pixel at depth d spans d / f metres across the ray; on a surface seen
        # at angle theta to its normal it stretches by 1 / cos(theta) (capped at 4x, grazing).
        rays = pts - torch.tensor(cam.c2w[:3, 3], dtype=torch.float32, device=d.device)
        rays = rays / rays.norm(dim=-1, keepdim=True)
        cos = (nrm * -rays).sum(-1).abs().clamp_min(1.0 / max_stretch)
        cos = torch.where(nrm.abs().sum(-1) > 0, cos, torch.ones_like(cos))
        foot = d / float(np.sqrt(cam.K[0, 0] * cam.K[1, 1])) / cos
        lo = torch.tensor(box[0], dtype=torch.float32, device=d.device)
        hi = torch.tensor(box[1], dtype=torch.float32, device=d.device)
        ok &= ((pts >= lo) & (pts <= hi)).all(-1)
        parts.append(PointCloud(pts[ok].cpu().numpy(), img.permute(1, 2, 0)[ok].cpu().numpy(),
                                nrm[ok].cpu().numpy(), foot[ok].cpu().numpy()))
    return PointCloud.concat(parts)


def run_mvs(images: list[np.ndarray], cams: list[Camera], box: np.ndarray, cfg: MVSConfig, *,
            device: str = "cpu", progress: bool = False, max_stretch: float = 4.0) -> tuple[PointCloud, list[np.ndarray], dict]:
    """The whole pipeline on one scene's aerial views.

    images: float32 [H, W, 3] in [0, 1] per view; cams: their cameras; box: [2, 3] region.
    Returns (fused cloud, filtered depth maps [H, W] (NaN = none), stats dict).
    """
    from tqdm import tqdm

    assert len(images) == len(cams), (len(images), len(cams))
    imgs = [torch.as_tensor(np.ascontiguousarray(i), device=device).permute(2, 0, 1).float() for i in images]
    sources = select_sources(cams, box, cfg)
    raw = [plane_sweep(imgs, cams, r, sources[r], box, cfg)
           for r in tqdm(range(len(cams)), desc="mvs", disable=None if progress else True, leave=False)]
    # Consistency is checked against every view that shares sources either way.
    neighbours = [sorted(set(sources[r]) | {s for s in range(len(cams)) if r in sources[s]}) for r in range(len(cams))]
    filt = consistency_filter(raw, cams, neighbours, cfg)
    cloud = fuse(filt, imgs, cams, box, max_stretch=max_stretch)
    n_pix = sum(d.numel() for d in raw)
    stats = {
        "views": len(cams), "views_without_sources": sum(1 for s in sources if not s),
        "raw_coverage": float(sum(torch.isfinite(d).sum().item() for d in raw) / max(n_pix, 1)),
        "filtered_coverage": float(sum(torch.isfinite(d).sum().item() for d in filt) / max(n_pix, 1)),
        "points": len(cloud),
    }
    return cloud, [d.cpu().numpy() for d in filt], stats
