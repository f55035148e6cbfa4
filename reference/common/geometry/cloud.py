"""A fused, coloured point cloud (what `mvs` fuses and `splat` draws) and the street prior on it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class PointCloud:
    """A fused, coloured point cloud. Arrays are numpy (saved with the method's checkpoint).

    xyz [N, 3] world (m); rgb [N, 3] in [0, 1]; normals [N, 3] unit (zero where unknown);
    footprint [N] the side of the source pixel on the surface (m).
    """

    xyz: np.ndarray
    rgb: np.ndarray
    normals: np.ndarray
    footprint: np.ndarray

    def __len__(self) -> int:
        return len(self.xyz)

    def subset(self, keep: np.ndarray) -> "PointCloud":
        return PointCloud(self.xyz[keep], self.rgb[keep], self.normals[keep], self.footprint[keep])

    @staticmethod
    def empty() -> "PointCloud":
        z = np.zeros((0, 3), np.float32)
        return PointCloud(z, z.copy(), z.copy(), np.zeros(0, np.float32))

    @staticmethod
    def concat(parts: list["PointCloud"]) -> "PointCloud":
        parts = [p for p in parts if len(p)]
        if not parts:
            return PointCloud.empty()
        return PointCloud(*(np.concatenate([getattr(p, k) for p in parts]) for k in ("xyz", "rgb", "normals", "footprint")))


# --------------------------------------------------------------------------- street prior


def ground_height(cloud: PointCloud, *, below: float | None = None, bin_m: float = 0.1,
                  smooth_m: float = 0.5, min_points: int = 20) -> float | None:
    """Height (world z, m) of the street: the mode of the heights of the lower half of the
    cloud's points under `below` (histogram of `bin_m` bins smoothed over `smooth_m`). Assumes a
    level street within the lane's region, true of SynthTown and of most city blocks; None when
    fewer than `min_points` points lie under `below` (no street to find).

    The street is the one surface every lane's views share and the most common height among the
    lower half of the points (roofs are many heights, facades spread over all of them). `below`:
    the street lies under the ground cameras that drive on it (`street_ceiling`); without it the
    sparse SynthTown smoke cloud (48x48) of one lane gave 1.99 m, the cameras' eye level (they
    are 2.0 m above the street), and snapping to that put the street through the cameras; with
    it, 0.09 m."""
    return street_height(cloud.xyz[:, 2], below=below, bin_m=bin_m, smooth_m=smooth_m, min_points=min_points)


def street_height(heights: np.ndarray, *, below: float | None = None, bin_m: float = 0.1, smooth_m: float = 0.5,
                  min_points: int = 20, share: float = 0.5) -> float | None:
    """`ground_height` of any points' heights (world z, m): of a fused cloud's, or of a Gaussian
    prior's means (`warp.prior_ground`); the mode of the lowest `share` of those under `below`
    (a Gaussian prior has few points under the cameras besides the street's: there the lower
    half would be the street's underside, 0.2 m low on SynthTown's first test lane)."""
    z = np.sort(np.asarray(heights, dtype=np.float64).ravel())
    if below is not None:
        z = z[z < below]
    if len(z) < max(min_points, 1):
        return None
    low = z[: max(1, int(len(z) * share))]
    lo = low[0]
    edges = np.arange(lo, max(low[-1], lo) + 2 * bin_m, bin_m)
    hist, edges = np.histogram(low, bins=edges)
    k = max(1, int(round(smooth_m / bin_m)))
    smooth = np.convolve(hist, np.ones(k) / k, mode="same")
    i = int(np.argmax(smooth))
    return float(edges[i] + bin_m / 2)


#: The least height (m) of a ground camera over the street it drives on: a car's roof camera is
#: 1.5-2.5 m up (SynthTown 2.0 m, the paper's capture likewise car-mounted).
MIN_CAMERA_CLEARANCE_M = 0.5


def street_ceiling(camera_heights) -> float | None:
    """The height the street lies under: the lowest ground camera less `MIN_CAMERA_CLEARANCE_M`
    (None without cameras)."""
    z = np.asarray(camera_heights, dtype=np.float64)
    return float(z.min()) - MIN_CAMERA_CLEARANCE_M if z.size else None


def snap_to_plane(cloud: PointCloud, plane: tuple[np.ndarray, float], band: float) -> PointCloud:
    """Points within `band` m of the plane (either side) moved onto it along its normal, with
    the plane's normal; points more than `band` below it dropped (no surface lies under the
    street); the rest unchanged. Stereo puts the street, seen through 70 m of air at 45 degrees,
    up to a metre off its height, and from a ground camera 2 m above it that smears the road up
    towards the horizon; this is MVS's planar prior for the one plane every lane has."""
    if len(cloud) == 0 or band <= 0:
        return cloud
    n, d = plane
    h = cloud.xyz.astype(np.float64) @ n - d
    keep = h >= -band
    near = np.abs(h) <= band
    xyz = np.where(near[:, None], cloud.xyz - h[:, None] * n, cloud.xyz).astype(np.float32)
    normals = np.where(near[:, None], n.astype(np.float32), cloud.normals)
    return PointCloud(xyz, cloud.rgb, normals, cloud.footprint).subset(keep)
