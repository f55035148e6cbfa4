"""The region a lane's ground cameras can see: the box every reconstruction is cropped to."""

from __future__ import annotations

import numpy as np

from skyeyes_bench.cameras import Camera
from skyeyes_bench.data.layout import Frame


def region_box(ground_frames: list[Frame], margin_m: float, z_range: tuple[float, float]) -> np.ndarray:
    """[2, 3] axis-aligned box (min, max) around the ground cameras: the region they can see.

    Horizontal: camera positions +- margin_m; vertical: z_range (m) in world coordinates.
    """
    c = np.array([f.c2w[:3, 3] for f in ground_frames])
    lo = np.array([c[:, 0].min() - margin_m, c[:, 1].min() - margin_m, z_range[0]])
    hi = np.array([c[:, 0].max() + margin_m, c[:, 1].max() + margin_m, z_range[1]])
    return np.stack([lo, hi])


def in_box(xyz: np.ndarray, box: np.ndarray) -> np.ndarray:
    return np.all((xyz >= box[0]) & (xyz <= box[1]), axis=-1)


def rays_hit_box(cam: Camera, box: np.ndarray) -> np.ndarray:
    """[H, W] bool: the pixel's ray crosses the box [2, 3] in front of the camera (slab test)."""
    _, d = cam.rays(normalize=False)
    d = d.reshape(cam.height, cam.width, 3)
    o = cam.c2w[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (box[0] - o) / d
        t1 = (box[1] - o) / d
    tmin = np.nanmax(np.minimum(t0, t1), -1)
    tmax = np.nanmin(np.maximum(t0, t1), -1)
    return (tmax >= np.maximum(tmin, 0)) & (tmax > 0)
