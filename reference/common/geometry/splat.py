"""A fused point cloud as surface discs, rendered into any camera.

Every point of an MVS cloud stands for the patch of surface one aerial pixel saw: a disc of
diameter `footprint` (m) around the point, lying in the plane of its normal (a point without a
normal is a sphere of that size). `surfels` turns the cloud into flat Gaussians (scale
footprint / 2 in the disc's plane, 1% of that across it); `render_cloud` draws them with the
Gaussian rasterizer at opacity `opacity` (0.98 by default). Composited front to back, nearly
opaque discs are a z-buffer whose edges are soft: the nearest surface covering a pixel gives
its colour, discs within a disc's thickness of each other blend. Pixels that no disc covers
show the background image the caller passes (`reference.common.appearance.Backgrounds`: one
colour above the horizon, one below), never a guess at the scene.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from reference.common.geometry.cloud import PointCloud
from skyeyes_bench.cameras import Camera


def voxel_downsample(cloud: PointCloud, voxel: float) -> PointCloud:
    """One point per occupied voxel of side `voxel` (m): mean position, colour and normal
    (renormalised), footprint the mean footprint but at least the voxel side."""
    if len(cloud) == 0 or voxel <= 0:
        return cloud
    keys = np.floor(cloud.xyz / voxel).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    m = len(counts)

    def mean(a: np.ndarray) -> np.ndarray:
        out = np.zeros((m,) + a.shape[1:], np.float64)
        np.add.at(out, inv, a)
        return out / counts.reshape((-1,) + (1,) * (a.ndim - 1))

    n = mean(cloud.normals)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(norm > 1e-6, n / np.maximum(norm, 1e-12), 0.0)
    foot = np.maximum(mean(cloud.footprint), voxel)
    return PointCloud(mean(cloud.xyz).astype(np.float32), mean(cloud.rgb).astype(np.float32),
                      n.astype(np.float32), foot.astype(np.float32))


def disc_rotations(normals: np.ndarray) -> np.ndarray:
    """[N, 4] wxyz quaternions of rotations taking +z to each unit normal (identity for a zero
    normal)."""
    n = np.asarray(normals, np.float64)
    ok = np.linalg.norm(n, axis=1) > 0.5
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(np.broadcast_to(z, n.shape), n)
    s = np.linalg.norm(axis, axis=1)
    c = n[:, 2]
    angle = np.arctan2(s, c)
    # Antiparallel normals (s = 0, c < 0): any axis in the xy plane.
    axis = np.where((s < 1e-9)[:, None], np.array([1.0, 0.0, 0.0]), axis / np.maximum(s, 1e-12)[:, None])
    rotvec = np.where(ok[:, None], axis * angle[:, None], 0.0)
    xyzw = Rotation.from_rotvec(rotvec).as_quat()
    return np.concatenate([xyzw[:, 3:], xyzw[:, :3]], 1).astype(np.float32)


def surfels(cloud: PointCloud, *, size: float = 1.0, thickness: float = 0.01) -> dict[str, torch.Tensor]:
    """Gaussian parameters of the cloud's discs: means [N, 3], quats [N, 4] wxyz, scales [N, 3]
    (m), colours [N, 3]. Disc radius = size * footprint / 2; across the disc `thickness` times
    that. Points without a normal get spheres. On the CPU (from the cloud's numpy arrays); the
    caller moves them to its device."""
    r = np.maximum(size * cloud.footprint.astype(np.float64) / 2, 1e-4)
    has_n = np.linalg.norm(cloud.normals, axis=1) > 0.5
    scales = np.stack([r, r, np.where(has_n, r * thickness, r)], 1)
    cpu = torch.device("cpu")
    return {"means": torch.tensor(cloud.xyz, dtype=torch.float32, device=cpu),
            "quats": torch.as_tensor(disc_rotations(cloud.normals), device=cpu),
            "scales": torch.tensor(scales, dtype=torch.float32, device=cpu),
            "colors": torch.tensor(cloud.rgb, dtype=torch.float32, device=cpu)}


def ground_colour(cloud: PointCloud, *, layer_m: float = 0.5) -> np.ndarray | None:
    """Median colour [3] of the cloud's lowest layer (points within `layer_m` of its 2nd
    percentile height): the road and pavement. None for an empty cloud."""
    if len(cloud) == 0:
        return None
    z0 = np.percentile(cloud.xyz[:, 2], 2)
    low = cloud.xyz[:, 2] <= z0 + layer_m
    return np.median(cloud.rgb[low], axis=0).astype(np.float32)


@torch.no_grad()
def render_surfels(params: dict[str, torch.Tensor], cam: Camera, *, opacity: float = 0.98, near: float = 0.5,
                   device: str | torch.device = "cpu") -> dict[str, np.ndarray]:
    """Render surfels (`surfels(...)`; moved to `device` where they are elsewhere) from `cam`:
    colour, coverage and depth.

    Returns float32 arrays: "colour" [H, W, 3] in [0, 1] (the discs' own colour where alpha > 0,
    0 elsewhere), "alpha" [H, W] (the coverage), "depth" [H, W] (the discs' planar depth in
    metres, averaged with their compositing weights; 0 where alpha is 0). A disc's depth is its
    centre's, so on a plane facing the camera the depth is exact and elsewhere off by at most a
    disc's depth extent.
    """
    from reference.common.gaussians.model import rgb_to_sh0
    from reference.common.gaussians.render import rasterize

    params = {k: v.to(device) for k, v in params.items()}  # no copy where they are on `device`
    means = params["means"]
    n = means.shape[0]
    if n == 0:
        zeros = np.zeros((cam.height, cam.width), np.float32)
        return {"colour": np.zeros((cam.height, cam.width, 3), np.float32), "alpha": zeros, "depth": zeros.copy()}
    dev = means.device
    sh = rgb_to_sh0(params["colors"])[:, None, :]
    w2c = torch.tensor(cam.w2c, dtype=torch.float32, device=dev)
    K = torch.tensor(cam.K, dtype=torch.float32, device=dev)
    out = rasterize(means, params["quats"], params["scales"], torch.full((n,), opacity, device=dev), sh, w2c, K,
                    cam.width, cam.height, near=near, sh_degree=0)
    alpha = out["alpha"]
    colour = out["rgb"] / alpha.clamp_min(1e-6)[..., None] * (alpha[..., None] > 0)  # composited over black
    return {"colour": colour.clamp(0, 1).cpu().numpy().astype(np.float32),
            "alpha": alpha.cpu().numpy().astype(np.float32),
            "depth": out["depth"].cpu().numpy().astype(np.float32)}


def render_cloud(params: dict[str, torch.Tensor], cam: Camera, *, opacity: float = 0.98, near: float = 0.5,
                 device: str | torch.device = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Render surfels (`surfels(...)`, moved to `device` where they are elsewhere) from `cam`.

    Returns (colour float32 [H, W, 3] in [0, 1], the discs' own colour where alpha > 0 and 0
    elsewhere; alpha float32 [H, W], the coverage). Composite with `over`. Depth as well:
    `render_surfels`.
    """
    out = render_surfels(params, cam, opacity=opacity, near=near, device=device)
    return out["colour"], out["alpha"]


def over(colour: np.ndarray, alpha: np.ndarray, background: np.ndarray) -> np.ndarray:
    """colour [H, W, 3] with coverage alpha [H, W] composited over background [H, W, 3]."""
    a = alpha[..., None]
    return (colour * a + background * (1 - a)).astype(np.float32)
