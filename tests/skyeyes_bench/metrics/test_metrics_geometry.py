"""Seen masks and warps (skyeyes_bench.metrics.geometry) on scenes whose answer is a closed form:
a wall hiding half the street, textured planes warped exactly, a one-pixel shift, and depths of
0, +inf (sky), NaN and cameras facing away."""

import numpy as np
import pytest

from skyeyes_bench.cameras import Camera, intrinsics
from skyeyes_bench.metrics import geometry as G

WALL_H = 30.0  # the wall: the plane x = 0, from z = 0 to z = WALL_H, infinite along y


def cast(cam: Camera, *, wall: bool = True) -> np.ndarray:
    """Planar depth [H, W] of the street scene: ground z = 0 (and the wall), sky = +inf."""
    o, d = cam.rays(normalize=False)  # camera z = 1: t is planar depth
    t = np.full(len(d), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = -o[:, 2] / d[:, 2]
        t = np.where((d[:, 2] < 0) & (tg > 0), tg, t)
        if wall:
            tw = -o[:, 0] / d[:, 0]
            zw = o[:, 2] + tw * d[:, 2]
            t = np.where((tw > 0) & (zw >= 0) & (zw <= WALL_H) & (tw < t), tw, t)
    return t.reshape(cam.height, cam.width)


def cam_at(pos, yaw, pitch, size, fov=90.0) -> Camera:
    return Camera.from_ypr(pos, yaw, pitch, fov_deg=fov, width=size, height=size)


def world_x(depth, cam):
    pts, _, _ = G.homogeneous_points(depth, cam)
    return pts[:, 0].reshape(depth.shape)


# --------------------------------------------------------------------------- seen masks


def test_wall_hides_half_the_street():
    # An aerial camera at x = -22, 52 m up, pitch -45, facing +x over the wall: the line from it
    # over the wall's top reaches the ground at x = 22 * 30 / (52 - 30) = 30, so the street
    # between the wall and x = 30 is hidden. A ground camera looking straight down from 10 m
    # at x = 30 sees x in [20, 40]: exactly half of it (x < 30) is hidden.
    aerial = [cam_at([-22.0, 0.0, 52.0], 0.0, -45.0, 256),
              cam_at([-22.0, 0.0, 52.0], 180.0, -45.0, 256),  # faces away from the street
              cam_at([-22.0, 5.0, 52.0], 0.0, -45.0, 256)]  # beside the first: the same shadow line
    depths = np.stack([cast(c) for c in aerial])
    ground = cam_at([30.0, 0.0, 10.0], 0.0, -90.0, 64)
    gdepth = cast(ground)
    x = world_x(gdepth, ground)
    assert np.mean(x > 30.0) == 0.5  # the expected seen share, by symmetry
    seen = G.seen_mask(gdepth, ground, depths, aerial, 0.01)
    # The test reads the 4 aerial pixel centres around a projection, so within one aerial pixel
    # of the shadow line (its footprint on the ground there: ~0.55 m) a hidden point may pass.
    foot = 73.5 * (np.pi / 2 / 256) * np.sqrt(2)
    assert seen[x > 30.0].all()
    assert not seen[x < 30.0 - 1.5 * foot].any()
    assert 0.5 <= seen.mean() <= 0.5 + 1.5 * foot / 20.0 + 1 / 64
    # without the wall everything in view is seen; the camera facing away alone sees nothing
    assert G.seen_mask(gdepth, ground, np.stack([cast(c, wall=False) for c in aerial]), aerial, 0.01).all()
    assert not G.seen_mask(gdepth, ground, depths[1:2], aerial[1:2], 0.01).any()


def test_one_camera_chunk_or_many_give_the_same_mask():
    aerial = [cam_at([-22.0 + 3 * k, 2.0 * k, 52.0], 10.0 * k, -45.0, 64) for k in range(5)]
    depths = np.stack([cast(c) for c in aerial])
    ground = cam_at([30.0, 0.0, 2.0], 20.0, -20.0, 32)
    gdepth = cast(ground)
    a = G.seen_mask(gdepth, ground, depths, aerial, 0.01, chunk=1)
    b = G.seen_mask(gdepth, ground, depths, aerial, 0.01, chunk=8)
    # slow reference: each pixel against each camera, written out with Camera.project
    pts, w, valid = G.homogeneous_points(gdepth, ground)
    ref = np.zeros(len(pts), bool)
    for c, d in zip(aerial, depths):
        for n in np.flatnonzero(valid):
            if w[n] > 0:
                uv, z = c.project(pts[n:n + 1])
            else:
                cz = pts[n] @ c.c2w[:3, :3]
                uv, z = (c.K[:2, :2] @ (cz[:2] / cz[2]) + c.K[:2, 2])[None] if cz[2] > 0 else np.full((1, 2), np.nan), \
                    np.array([cz[2]])
            if not (z[0] > 0 and 0 <= uv[0, 0] < c.width and 0 <= uv[0, 1] < c.height):
                continue
            x, y = uv[0] - 0.5
            js = {int(np.clip(np.floor(x) + k, 0, c.width - 1)) for k in (0, 1)}
            is_ = {int(np.clip(np.floor(y) + k, 0, c.height - 1)) for k in (0, 1)}
            dmax = max(d[i, j] for i in is_ for j in js)
            ref[n] |= (z[0] <= dmax * 1.01) if w[n] > 0 else np.isposinf(dmax)
    assert (a == b).all() and (a.ravel() == ref).all()
    assert 0.05 < a.mean() < 0.95  # the scene has both (sky above the horizon is unseen here)


def test_sky_is_seen_only_by_a_view_that_sees_sky_in_that_direction():
    ground = cam_at([30.0, 0.0, 2.0], 0.0, 0.0, 32)  # level: the upper half is sky
    gdepth = cast(ground, wall=False)
    sky = np.isposinf(gdepth)
    assert 0.4 < sky.mean() < 0.6
    down = [cam_at([-22.0, 0.0, 52.0], 0.0, -45.0, 64)]  # sees no sky above the horizon
    up = [cam_at([0.0, 0.0, 100.0], 0.0, 20.0, 64, fov=120.0)]  # sees the sky ahead
    seen_down = G.seen_mask(gdepth, ground, np.stack([cast(c, wall=False) for c in down]), down, 0.01)
    seen_up = G.seen_mask(gdepth, ground, np.stack([cast(c, wall=False) for c in up]), up, 0.01)
    assert not seen_down[sky].any() and seen_down[~sky].mean() > 0.9
    assert seen_up[sky].all()


def test_invalid_depths_are_unseen_and_never_nan():
    aerial = [cam_at([-22.0, 0.0, 52.0], 0.0, -45.0, 64)]
    adepth = np.stack([cast(c, wall=False) for c in aerial])
    ground = cam_at([30.0, 0.0, 10.0], 0.0, -90.0, 16)
    gdepth = cast(ground, wall=False)
    assert G.seen_mask(gdepth, ground, adepth, aerial, 0.01).all()
    bad = gdepth.copy()
    bad[0, :4] = [0.0, np.nan, -3.0, -np.inf]
    seen = G.seen_mask(bad, ground, adepth, aerial, 0.01)
    assert not seen[0, :4].any() and seen[1:].all()
    # aerial depth invalid everywhere: nothing is seen (and nothing is NaN)
    junk = np.full_like(adepth, np.nan)
    junk[0, ::2] = 0.0
    assert not G.seen_mask(gdepth, ground, junk, aerial, 0.01).any()
    # no aerial view at all
    assert not G.seen_mask(gdepth, ground, np.zeros((0, 4, 4)), [], 0.01).any()


# --------------------------------------------------------------------------- warps


def plane_views(shift_px: float, texture, *, size=48, z=10.0, cx_offset=0.0):
    """Two cameras looking along +z at the plane z = Z (depth Z everywhere); the second is moved
    along x so the plane moves by `shift_px` pixels. texture(X, Y) -> [N, 3] colours."""
    f = size / 2.0
    K = intrinsics(90.0, size, size)
    cams = []
    for k in range(2):
        c2w = np.eye(4)
        c2w[0, 3] = k * shift_px * z / f
        cams.append(Camera(K, c2w, size, size))
    images = []
    for k, c in enumerate(cams):
        kk = K.copy()
        if k == 0:
            kk[0, 2] += cx_offset  # frame t rendered with its content moved by cx_offset pixels
        o, d = Camera(kk, c.c2w, size, size).rays(normalize=False)
        p = o + d * z
        images.append(texture(p[:, 0], p[:, 1]).reshape(size, size, 3))
    return cams, images, np.full((size, size), z)


def linear(x, y):
    return np.stack([0.5 + 0.01 * x, 0.5 + 0.02 * x - 0.005 * y, 0.4 + 0.003 * y], axis=1)


def test_warping_the_ground_truth_gives_the_floor_within_resampling_error():
    cams, (src, dst), depth = plane_views(2.37, linear)
    uv, valid = G.warp_coords(depth, cams[1], depth, cams[0], 0.01)
    err, n = G.warp_error(src, dst, uv, valid)
    # a linear texture is reproduced exactly by bilinear resampling
    assert n > 0.8 * depth.size and err < 1e-12
    # out of view: the destination columns whose point lies beyond the source's pixel centres
    assert not valid[:, -2:].any() and valid[:, :40].all()
    # a sinusoid: |error| <= max |f''| / 8 per pixel (linear interpolation, spacing 1)
    amp, k = 0.2, 1.3  # texture 0.5 + amp sin(k X); in pixels: frequency k Z / f = 0.54 rad/px
    cams, (src, dst), depth = plane_views(2.37, lambda x, y: np.repeat((0.5 + amp * np.sin(k * x))[:, None], 3, 1))
    uv, valid = G.warp_coords(depth, cams[1], depth, cams[0], 0.01)
    err, n = G.warp_error(src, dst, uv, valid)
    bound = amp * (k * 10.0 / 24.0) ** 2 / 8
    assert 0.1 * bound < err <= bound


def test_one_pixel_shift_raises_the_error_by_the_gradient():
    # frame t shifted by one pixel: the linear texture's colour changes by slope * Z / f per pixel
    # in each channel, so the warp error rises from 0 to mean_c |s_c| * Z / f exactly.
    cams, (src, dst), depth = plane_views(3.0, linear)
    _, (shifted, _), _ = plane_views(3.0, linear, cx_offset=1.0)
    uv, valid = G.warp_coords(depth, cams[1], depth, cams[0], 0.01)
    base, _ = G.warp_error(src, dst, uv, valid)
    moved, _ = G.warp_error(shifted, dst, uv, valid)
    expected = np.mean([0.01, 0.02, 0.0]) * 10.0 / 24.0  # X slopes per channel; Y does not change
    assert base < 1e-12
    assert moved == pytest.approx(expected, rel=1e-9)


def test_occluded_pixels_are_masked():
    cams, (src, dst), depth = plane_views(2.0, linear)
    near = depth.copy()
    near[10:20, 10:20] = 3.0  # something in front of the plane in frame t only
    uv, valid = G.warp_coords(depth, cams[1], near, cams[0], 0.01)
    ref_uv, ref_valid = G.warp_coords(depth, cams[1], depth, cams[0], 0.01)
    hidden = ref_valid & ~valid
    assert hidden.sum() >= 80  # ~ the 10 x 10 block, seen from t + 1 (shifted by 2 pixels)
    u = ref_uv[hidden][:, 0]
    assert (u > 9.5 - 1).all() and (u < 20.5 + 1).all()
    # and a destination point *in front of* everything the source saw there is not a correspondence
    far = depth.copy()
    far[30:40, 30:40] = 50.0
    _, valid_far = G.warp_coords(depth, cams[1], far, cams[0], 0.01)
    assert (ref_valid & ~valid_far).sum() >= 80


def test_warp_depth_edge_cases_give_no_nan():
    cams, (src, dst), depth = plane_views(2.0, linear)
    bad = depth.copy()
    bad[0, :4] = [0.0, np.nan, -1.0, -np.inf]
    uv, valid = G.warp_coords(bad, cams[1], depth, cams[0], 0.01)
    assert not valid[0, :4].any() and np.isnan(uv[0, :4]).all()
    # sky in both views: warped by rotation alone (the translation does not move a direction)
    sky = np.full_like(depth, np.inf)
    uv, valid = G.warp_coords(sky, cams[1], sky, cams[0], 0.01)
    assert valid[1:-1, 1:-1].all()
    centres = cams[1].pixel_centers().reshape(uv.shape)
    assert np.allclose(uv[valid], centres[valid])
    # sky in the destination, a surface in the source: not the same point
    assert not G.warp_coords(sky, cams[1], depth, cams[0], 0.01)[1].any()
    # the source camera faces away: nothing projects, the error is (NaN, 0), not a NaN mean
    away = Camera(cams[0].K, cams[0].c2w @ np.diag([-1.0, 1.0, -1.0, 1.0]), 48, 48)
    uv, valid = G.warp_coords(depth, cams[1], depth, away, 0.01)
    assert not valid.any()
    err, n = G.warp_error(src, dst, uv, valid)
    assert n == 0 and np.isnan(err)


def test_sample_bilinear_at_centres_and_between():
    img = np.arange(12, dtype=np.float64).reshape(3, 4, 1)
    uv = np.array([[0.5, 0.5], [3.5, 2.5], [1.0, 0.5], [1.5, 1.0]])
    got = G.sample_bilinear(img, uv)[:, 0]
    assert got == pytest.approx([0.0, 11.0, 0.5, 3.0])


def test_clean_depth_keeps_every_positive_depth():
    """Depths below 1 m are valid (a facade next to the camera); 0, negatives, NaN and -inf are
    not; +inf (sky) is kept; the input is not modified."""
    d = np.array([[0.05, 0.999, 1.0, 250.0], [0.0, -0.5, np.nan, -np.inf], [np.inf, 1e-6, 3.0, 2.0]], np.float32)
    got = G.clean_depth(d)
    want = np.array([[0.05, 0.999, 1.0, 250.0], [np.nan] * 4, [np.inf, 1e-6, 3.0, 2.0]])
    np.testing.assert_allclose(got, want.astype(np.float32).astype(np.float64), equal_nan=True)
    assert got.dtype == np.float64 and d[1, 0] == 0.0
