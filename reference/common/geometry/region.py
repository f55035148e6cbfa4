"""The region a lane's ground cameras can see: the box every reconstruction is cropped to."""

from __future__ import annotations

import numpy as np

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
