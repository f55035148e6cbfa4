"""Depth-and-pose geometry of the seen/unseen and warp-consistency metrics (docs/metrics.md).

Pure numpy on arrays and `cameras.Camera`s (docs/formats.md conventions: OpenCV camera axes, `c2w`
camera-to-world, planar depth in metres, pixel (i, j) centred at (j + 0.5, i + 0.5)).

**Depth values.** A ground-truth depth is *valid* if it is finite and > 0 (a surface point) or
+inf (sky: a point at infinity, i.e. a direction). 0, negative, NaN and -inf are *invalid*: no
point can be placed there, so such a pixel is never "seen" and never part of a warp.

**The depth test** (both metrics). A point projected into a camera at (u, v) with planar depth z
is compared with the camera's depth at the (up to) four pixel centres around (u, v), the pixels a
bilinear lookup would read, with invalid depths left out: d_min and d_max. On a continuous
surface the point's own depth lies within [d_min, d_max] (planar depth of a plane is monotonic
between pixel centres), so the tests need no slope term:

* *visible* (not occluded): z <= d_max * (1 + tol). A point at infinity: d_max = +inf.
* *consistent* (the warp's correspondence; also excludes geometry seen in front of everything
  the camera saw there): d_min * (1 - tol) <= z <= d_max * (1 + tol). At infinity: d_min = +inf.

`tol` is the protocol's `depth_tolerance` (relative). Cameras that face away (z <= 0) and
projections outside the image never pass.
"""

from __future__ import annotations

import numpy as np

from ..cameras import Camera


def clean_depth(depth: np.ndarray) -> np.ndarray:
    """float64 copy of depth [..., H, W]: invalid values (0, < 0, NaN, -inf) -> NaN; +inf kept."""
    d = np.array(depth, dtype=np.float64)
    d[~((d > 0) & ~np.isnan(d))] = np.nan  # NaN > 0 is False; -inf, 0 and negatives fail too
    return d


def homogeneous_points(depth: np.ndarray, cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The world points of every pixel: (points [H*W, 3], w [H*W], valid [H*W]), row-major.

    w = 1: a surface point at its finite depth; w = 0: a direction (sky, depth +inf), stored as
    the unit-free ray direction with camera z = 1; invalid depths get valid False (and zeros).
    """
    depth = np.asarray(depth)
    assert depth.shape == (cam.height, cam.width), (depth.shape, cam.height, cam.width)
    d = clean_depth(depth).ravel()  # [N]
    o, dirs = cam.rays(normalize=False)  # [N, 3] each; camera z = 1, so t is planar depth
    finite = np.isfinite(d)
    sky = np.isposinf(d)
    pts = np.zeros_like(dirs)
    pts[finite] = o[finite] + dirs[finite] * d[finite, None]
    pts[sky] = dirs[sky]
    return pts, finite.astype(np.float64), finite | sky


def project(points: np.ndarray, w: np.ndarray, c2ws: np.ndarray, Ks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Homogeneous world points into A cameras.

    Args:
        points: [N, 3] positions (w = 1) or directions (w = 0).
        w: [N] 1 or 0.
        c2ws: [A, 4, 4] camera-to-world; Ks: [A, 3, 3].

    Returns:
        uv [A, N, 2] pixel coordinates (NaN where z <= 0) and z [A, N] planar depth (for a
        direction: its camera z, > 0 when it points into the camera's half-space).
    """
    assert points.ndim == 2 and points.shape[1] == 3 and w.shape == (points.shape[0],), (points.shape, w.shape)
    assert c2ws.ndim == 3 and c2ws.shape[1:] == (4, 4) and Ks.shape == (c2ws.shape[0], 3, 3), (c2ws.shape, Ks.shape)
    rot, t = c2ws[:, :3, :3], c2ws[:, :3, 3]  # [A, 3, 3], [A, 3]
    # R^T (X - w t) row-wise = X R - w (t R); batched matmul (einsum was 4x slower here)
    cam = np.matmul(points[None], rot) - w[None, :, None] * np.matmul(t[:, None, :], rot)  # [A, N, 3]
    z = cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = cam[..., :2] / np.where(z > 0, z, np.nan)[..., None]
    uv = np.matmul(xy, np.swapaxes(Ks[:, :2, :2], 1, 2)) + Ks[:, None, :2, 2]  # [A, N, 2]
    return uv, z


def neighbour_depths(depths: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smallest and largest valid depth among the (up to) 4 pixel centres around each uv.

    Args:
        depths: [A, H, W] cleaned depths (`clean_depth`: NaN invalid, +inf sky).
        uv: [A, N, 2] pixel coordinates in the matching camera (NaN: not projected).

    Returns:
        d_min [A, N], d_max [A, N] (NaN where no neighbour is valid or uv is NaN), and inside
        [A, N]: uv lies within the image, [0, W) x [0, H). Neighbours are clamped to the image.
    """
    a, h, wd = depths.shape
    u, v = uv[..., 0], uv[..., 1]
    inside = (u >= 0) & (u < wd) & (v >= 0) & (v < h)  # False for NaN
    x = np.where(inside, u - 0.5, 0.0)
    y = np.where(inside, v - 0.5, 0.0)
    j0 = np.floor(x).astype(np.int64)
    i0 = np.floor(y).astype(np.int64)
    flat = depths.reshape(a, h * wd)
    base = (np.arange(a) * (h * wd))[:, None]
    dmin = np.full(u.shape, np.nan)
    dmax = np.full(u.shape, np.nan)
    for di in (0, 1):
        ii = np.clip(i0 + di, 0, h - 1)
        for dj in (0, 1):
            jj = np.clip(j0 + dj, 0, wd - 1)
            d = flat.ravel()[base + ii * wd + jj]
            dmin = np.fmin(dmin, d)  # fmin / fmax skip NaN (invalid depth)
            dmax = np.fmax(dmax, d)
    dmin[~inside] = np.nan
    dmax[~inside] = np.nan
    return dmin, dmax, inside


def _not_occluded(z: np.ndarray, w: np.ndarray, dmax: np.ndarray, tol: float) -> np.ndarray:
    """z <= d_max (1 + tol) for points (w = 1); d_max = +inf for directions (w = 0). NaN -> False."""
    with np.errstate(invalid="ignore"):
        return np.where(w > 0, z <= dmax * (1.0 + tol), np.isposinf(dmax)) & (z > 0)


def seen_mask(ground_depth: np.ndarray, ground_cam: Camera, aerial_depths: np.ndarray,
              aerial_cams: list[Camera], tol: float, *, chunk: int = 8) -> np.ndarray:
    """Which ground pixels at least one aerial camera sees (the depth test of the module doc).

    Args:
        ground_depth: [H, W] planar metres (+inf sky; invalid values -> not seen).
        ground_cam: the ground camera (H x W).
        aerial_depths: [A, h, w] planar metres of the aerial views (any invalid values allowed).
        aerial_cams: A cameras of size w x h.
        tol: relative depth tolerance.
        chunk: aerial cameras tested at once; the nearest are tested first and a pixel once seen
            is not tested again, which bounds both memory and time.

    Returns:
        bool [H, W].
    """
    assert aerial_depths.ndim == 3 and len(aerial_cams) == aerial_depths.shape[0], (aerial_depths.shape,
                                                                                      len(aerial_cams))
    pts, w, valid = homogeneous_points(ground_depth, ground_cam)
    seen = np.zeros(len(pts), dtype=bool)
    todo = np.flatnonzero(valid)
    if not len(aerial_cams):
        return seen.reshape(ground_depth.shape)
    dep = clean_depth(aerial_depths)
    c2ws = np.stack([c.c2w for c in aerial_cams])
    Ks = np.stack([c.K for c in aerial_cams])
    order = np.argsort(np.linalg.norm(c2ws[:, :3, 3] - ground_cam.c2w[:3, 3], axis=1), kind="stable")
    sees_sky = np.isposinf(dep).any(axis=(1, 2))  # [A]: only these can see a point at infinity
    for s in range(0, len(order), chunk):
        if not sees_sky[order[s:]].any():
            todo = todo[w[todo] > 0]
        if not len(todo):
            break
        idx = order[s:s + chunk]
        uv, z = project(pts[todo], w[todo], c2ws[idx], Ks[idx])
        _, dmax, inside = neighbour_depths(dep[idx], uv)
        hit = (inside & _not_occluded(z, w[todo][None, :], dmax, tol)).any(axis=0)
        seen[todo[hit]] = True
        todo = todo[~hit]
    return seen.reshape(ground_depth.shape)


def warp_coords(depth_dst: np.ndarray, cam_dst: Camera, depth_src: np.ndarray, cam_src: Camera,
                tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel of the destination view lies in the source view, and whether the source
    sees that same point there (backward warp for `sample_bilinear`).

    A destination pixel is valid when its depth is valid, its point lies in front of the source
    camera, projects within the source's pixel centres (u in [0.5, W - 0.5], v likewise, so the
    bilinear lookup never extrapolates), and passes the *consistent* depth test against the
    source depth (module doc): occluded and out-of-view pixels are masked.

    Args:
        depth_dst: [H, W] destination depth; cam_dst its camera.
        depth_src: [h, w] source depth; cam_src its camera.
        tol: relative depth tolerance.

    Returns:
        uv [H, W, 2] source pixel coordinates (NaN where invalid) and valid bool [H, W].
    """
    pts, w, valid = homogeneous_points(depth_dst, cam_dst)
    uv, z = project(pts, w, cam_src.c2w[None], cam_src.K[None])
    dmin, dmax, _ = neighbour_depths(clean_depth(depth_src)[None], uv)
    uv, z, dmin, dmax = uv[0], z[0], dmin[0], dmax[0]
    h, wd = np.asarray(depth_src).shape
    with np.errstate(invalid="ignore"):
        centred = (uv[:, 0] >= 0.5) & (uv[:, 0] <= wd - 0.5) & (uv[:, 1] >= 0.5) & (uv[:, 1] <= h - 0.5)
        front = np.where(w > 0, z >= dmin * (1.0 - tol), np.isposinf(dmin))
    ok = valid & centred & front & _not_occluded(z, w, dmax, tol)
    uv = np.where(ok[:, None], uv, np.nan)
    return uv.reshape(depth_dst.shape + (2,)), ok.reshape(depth_dst.shape)


def sample_bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of image [H, W, C] at pixel coordinates uv [N, 2] (centres at +0.5),
    clamped to the image (callers pass coordinates within the centres) -> float64 [N, C]."""
    img = np.asarray(image, dtype=np.float64)
    h, w = img.shape[:2]
    x = np.clip(uv[:, 0] - 0.5, 0.0, w - 1.0)
    y = np.clip(uv[:, 1] - 0.5, 0.0, h - 1.0)
    j0 = np.minimum(np.floor(x).astype(np.int64), w - 2) if w > 1 else np.zeros(len(x), np.int64)
    i0 = np.minimum(np.floor(y).astype(np.int64), h - 2) if h > 1 else np.zeros(len(y), np.int64)
    fx = (x - j0)[:, None]
    fy = (y - i0)[:, None]
    j1, i1 = np.minimum(j0 + 1, w - 1), np.minimum(i0 + 1, h - 1)
    top = img[i0, j0] * (1 - fx) + img[i0, j1] * fx
    bot = img[i1, j0] * (1 - fx) + img[i1, j1] * fx
    return top * (1 - fy) + bot * fy


def warp_error(src: np.ndarray, dst: np.ndarray, uv: np.ndarray, valid: np.ndarray) -> tuple[float, int]:
    """Mean absolute error of the source image warped into the destination view.

    Args:
        src: [h, w, 3] source frame (frame t) in [0, 1]; dst: [H, W, 3] destination (frame t + 1).
        uv, valid: from `warp_coords(depth t+1, cam t+1, depth t, cam t, tol)`.

    Returns:
        (mean over valid pixels and the 3 channels of |dst - warp(src)|, number of valid pixels);
        (NaN, 0) when no pixel is valid.
    """
    assert dst.shape[:2] == valid.shape and uv.shape == valid.shape + (2,), (dst.shape, uv.shape, valid.shape)
    n = int(valid.sum())
    if n == 0:
        return float("nan"), 0
    warped = sample_bilinear(src, uv[valid])  # [n, 3]
    return float(np.abs(np.asarray(dst, np.float64)[valid] - warped).mean()), n
