"""Cameras against hand-built arithmetic: CARLA and MatrixCity conversions, projection, rays."""

import numpy as np
import pytest

from skyeyes_bench.cameras import (
    Camera,
    K_from_dict,
    carla_points_to_world,
    focal_from_fov,
    from_carla,
    from_matrixcity,
    rigid_problem,
)
from skyeyes_bench.errors import UserError

W, H = 64, 48


def _carla_axes(pitch, yaw, roll):
    """Forward, right, up of a CARLA camera in CARLA's (left-handed) world, built by hand:
    forward from yaw/pitch; at roll 0 right is horizontal and up lies in the vertical plane of
    forward; positive roll turns right towards -up (CARLA: right wing down)."""
    p, y, r = np.deg2rad([pitch, yaw, roll])
    fwd = np.array([np.cos(p) * np.cos(y), np.cos(p) * np.sin(y), np.sin(p)])
    right0 = np.array([-np.sin(y), np.cos(y), 0.0])
    up0 = np.array([-np.cos(y) * np.sin(p), -np.sin(y) * np.sin(p), np.cos(p)])
    right = np.cos(r) * right0 - np.sin(r) * up0
    up = np.sin(r) * right0 + np.cos(r) * up0
    return fwd, right, up


FLIP = np.array([1.0, -1.0, 1.0])
ANGLES = [(0, 0, 0), (0, 90, 0), (10, 30, 0), (-45, 135, 0), (-90, 0, 0), (-90, 77, 0), (90, -30, 0),
          (0, 0, 30), (20, -120, -45), (-89.999, 10, 5), (0, 359.5, 0), (45, -180, 180)]


@pytest.mark.parametrize("pitch, yaw, roll", ANGLES)
def test_from_carla_axes(pitch, yaw, roll):
    loc = np.array([12.5, -3.0, 2.0])
    cam = from_carla(loc, (pitch, yaw, roll), 90.0, W, H)
    fwd, right, up = _carla_axes(pitch, yaw, roll)
    r = cam.c2w[:3, :3]
    np.testing.assert_allclose(r[:, 0], right * FLIP, atol=1e-12)  # camera x = right
    np.testing.assert_allclose(r[:, 1], -up * FLIP, atol=1e-12)  # camera y = down
    np.testing.assert_allclose(r[:, 2], fwd * FLIP, atol=1e-12)  # camera z = forward
    np.testing.assert_allclose(cam.c2w[:3, 3], loc * FLIP)
    np.testing.assert_allclose(cam.c2w[3], [0, 0, 0, 1])
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)
    assert rigid_problem(cam.c2w) is None


@pytest.mark.parametrize("pitch, yaw, roll", ANGLES)
def test_from_carla_projects_carla_points_like_the_simulator(pitch, yaw, roll):
    """A CARLA point a right / b up / d ahead of the camera appears at
    u = cx + f a / d, v = cy - f b / d after converting both the pose and the point."""
    loc = np.array([-4.0, 7.0, 30.0])
    fov = 70.0
    cam = from_carla(loc, (pitch, yaw, roll), fov, W, H)
    fwd, right, up = _carla_axes(pitch, yaw, roll)
    rng = np.random.default_rng(1)
    abd = np.stack([rng.uniform(-3, 3, 20), rng.uniform(-3, 3, 20), rng.uniform(1, 50, 20)], axis=1)
    pts_carla = loc + abd[:, :1] * right + abd[:, 1:2] * up + abd[:, 2:] * fwd
    uv, z = cam.project(carla_points_to_world(pts_carla))
    f = W / 2 / np.tan(np.deg2rad(fov) / 2)
    np.testing.assert_allclose(z, abd[:, 2], rtol=1e-10)
    np.testing.assert_allclose(uv[:, 0], W / 2 + f * abd[:, 0] / abd[:, 2], atol=1e-8)
    np.testing.assert_allclose(uv[:, 1], H / 2 - f * abd[:, 1] / abd[:, 2], atol=1e-8)


def test_carla_point_flip_is_y_negation():
    pts = np.array([[1.0, 2.0, 3.0], [-4.0, -5.0, 6.0]])
    np.testing.assert_array_equal(carla_points_to_world(pts), [[1, -2, 3], [-4, 5, 6]])


def test_carla_yaw_heading_in_our_world():
    # CARLA yaw +90 faces CARLA +y, which is our -y (the world's y is flipped).
    np.testing.assert_allclose(from_carla((0, 0, 0), (0, 90, 0), 90, W, H).forward, [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(from_carla((0, 0, 0), (0, 0, 0), 90, W, H).forward, [1, 0, 0], atol=1e-12)


@pytest.mark.parametrize("yaw", [-720.0, -180.0, -37.0, 0.0, 45.0, 179.0, 359.0])
def test_carla_yaw_wraps(yaw):
    a = from_carla((1, 2, 3), (-30, yaw, 10), 90, W, H).c2w
    for k in (-1, 1, 2):
        np.testing.assert_allclose(from_carla((1, 2, 3), (-30, yaw + 360 * k, 10), 90, W, H).c2w, a, atol=1e-12)
    np.testing.assert_allclose(from_carla((0, 0, 0), (0, -180, 0), 90, W, H).c2w,
                               from_carla((0, 0, 0), (0, 180, 0), 90, W, H).c2w, atol=1e-12)


@pytest.mark.parametrize("yaw", [0.0, 30.0, 90.0, 200.0])
def test_carla_nadir(yaw):
    cam = from_carla((5, 5, 52), (-90, yaw, 0), 90, W, H)
    np.testing.assert_allclose(cam.forward, [0, 0, -1], atol=1e-12)
    # The top of the image (-camera y) points along the heading, written in our world.
    heading = np.array([np.cos(np.deg2rad(yaw)), -np.sin(np.deg2rad(yaw)), 0.0])
    np.testing.assert_allclose(-cam.c2w[:3, 1], heading, atol=1e-12)
    # A ground point ahead lies in the upper half; the point below the camera at the centre.
    below = np.array([5.0, -5.0, 0.0])  # CARLA (5, 5, 0) in our world
    uv, z = cam.project(np.stack([below, below + 10 * heading]))
    np.testing.assert_allclose(uv[0], [W / 2, H / 2], atol=1e-9)
    assert z[0] == pytest.approx(52) and uv[1, 1] < H / 2
    # pitch +90 looks straight up
    np.testing.assert_allclose(from_carla((0, 0, 0), (90, yaw, 0), 90, W, H).forward, [0, 0, 1], atol=1e-12)


@pytest.mark.parametrize("fov", [1e-3, 0.5, 60.0, 90.0, 150.0, 179.0])
def test_fov_extremes(fov):
    cam = from_carla((0, 0, 0), (0, 0, 0), fov, W, H)
    f = W / (2 * np.tan(np.deg2rad(fov) / 2))
    assert cam.K[0, 0] == pytest.approx(f, rel=1e-12) and cam.K[1, 1] == pytest.approx(f, rel=1e-12)
    assert cam.fov_x_deg == pytest.approx(fov, rel=1e-9)
    # A ray at half the fov to the right hits the right image border.
    half = np.deg2rad(fov) / 2
    d = 1000.0
    p_carla = np.array([[d, d * np.tan(half) * 0.999999, 0.0]])  # CARLA +y = right
    uv, _ = cam.project(carla_points_to_world(p_carla))
    assert uv[0, 0] == pytest.approx(W * (0.5 + 0.5 * 0.999999), rel=1e-9)
    # rays at the border pixel centre make the expected angle with the axis
    _, dirs = cam.rays(np.array([[W - 0.5, H / 2]]))
    ang = np.arctan2(np.linalg.norm(np.cross(dirs[0], cam.forward)), dirs[0] @ cam.forward)
    assert ang == pytest.approx(np.arctan((W / 2 - 0.5) / f), rel=1e-9)


@pytest.mark.parametrize("fov", [0.0, -5.0, 180.0, 200.0])
def test_bad_fov(fov):
    with pytest.raises(UserError, match="field of view"):
        focal_from_fov(fov, W)


def _random_camera(seed=0):
    rng = np.random.default_rng(seed)
    return Camera.from_ypr(rng.normal(size=3) * 10, *rng.uniform(-180, 180, 1), *rng.uniform(-80, 80, 1),
                           *rng.uniform(-30, 30, 1), fov_deg=75.0, width=W, height=H)


def test_from_ypr_hand_axes():
    for yaw, pitch in [(0, 0), (90, 0), (30, -45), (-120, 60)]:
        cam = Camera.from_ypr((0, 0, 0), yaw, pitch, fov_deg=90, width=W, height=H)
        y, p = np.deg2rad([yaw, pitch])
        np.testing.assert_allclose(cam.forward, [np.cos(p) * np.cos(y), np.cos(p) * np.sin(y), np.sin(p)], atol=1e-12)
        np.testing.assert_allclose(cam.c2w[:3, 0], [np.sin(y), -np.cos(y), 0], atol=1e-12)  # right, level
        assert cam.c2w[2, 1] <= 1e-12  # camera y (down) never points up at roll 0


def test_project_unproject_round_trip():
    cam = _random_camera()
    rng = np.random.default_rng(2)
    uv = rng.uniform([0, 0], [W, H], size=(100, 2))
    depth = rng.uniform(0.1, 500, 100)
    pts = cam.unproject(uv, depth)
    uv2, z = cam.project(pts)
    np.testing.assert_allclose(uv2, uv, atol=1e-7)
    np.testing.assert_allclose(z, depth, rtol=1e-10)
    # planar depth: the camera-frame z of the point, computed with an explicit inverse
    cam_pts = (np.linalg.inv(cam.c2w) @ np.c_[pts, np.ones(100)].T).T
    np.testing.assert_allclose(cam_pts[:, 2], depth, rtol=1e-10)
    np.testing.assert_allclose(cam.w2c, np.linalg.inv(cam.c2w), atol=1e-12)


def test_points_behind_camera_are_nan():
    cam = _random_camera(3)
    uv, z = cam.project(np.stack([cam.center - cam.forward, cam.center + cam.forward]))
    assert z[0] < 0 and np.all(np.isnan(uv[0])) and np.all(np.isfinite(uv[1]))


def test_rays_through_pixel_centres():
    cam = _random_camera(4)
    o, d = cam.rays()
    assert o.shape == d.shape == (W * H, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(o, np.broadcast_to(cam.center, o.shape))
    kinv = np.linalg.inv(cam.K)
    for i, j in [(0, 0), (H - 1, W - 1), (7, 30)]:
        ray_cam = kinv @ [j + 0.5, i + 0.5, 1.0]
        expect = cam.c2w[:3, :3] @ ray_cam
        np.testing.assert_allclose(d[i * W + j], expect / np.linalg.norm(expect), atol=1e-12)
        uv, _ = cam.project(o[i * W + j][None] + 3.7 * d[i * W + j][None])
        np.testing.assert_allclose(uv[0], [j + 0.5, i + 0.5], atol=1e-9)
    _, d1 = cam.rays(normalize=False)
    np.testing.assert_allclose(d1 @ cam.forward, 1.0, atol=1e-12)  # planar: camera z = 1


def test_with_size_and_intrinsics_dict():
    cam = _random_camera(5)
    big = cam.with_size(2 * W, 2 * H)
    uv, _ = cam.project(cam.center[None] + 5 * cam.forward[None] + 0.3 * cam.c2w[:3, 0][None])
    uv2, _ = big.project(cam.center[None] + 5 * cam.forward[None] + 0.3 * cam.c2w[:3, 0][None])
    np.testing.assert_allclose(uv2, 2 * uv, atol=1e-9)
    np.testing.assert_allclose(K_from_dict(cam.intrinsics_dict()), cam.K)


# --------------------------------------------------------------------------- MatrixCity

GL = np.diag([1.0, -1.0, -1.0, 1.0])


def _file_matrix(cv_c2w, pose_format, convention):
    """What a MatrixCity JSON would hold for an OpenCV c2w in metres."""
    m = cv_c2w @ GL if convention == "opengl" else cv_c2w.copy()
    if pose_format == "raw":
        m[:3, :3] *= 0.01
    else:
        m[:3, 3] /= 100.0
    return m


@pytest.mark.parametrize("pose_format", ["raw", "paper"])
@pytest.mark.parametrize("convention", ["opengl", "opencv"])
def test_from_matrixcity_formats(pose_format, convention):
    truth = Camera.from_ypr((123.4, -56.7, 2.0), 33.0, -10.0, 4.0, fov_deg=80, width=W, height=H)
    stored = np.round(_file_matrix(truth.c2w, pose_format, convention), 7)  # the files hold ~7 digits
    cam = from_matrixcity(stored.tolist(), pose_format=pose_format, convention=convention,
                          fov_deg=80, width=W, height=H)
    np.testing.assert_allclose(cam.c2w, truth.c2w, atol=2e-5)
    assert np.linalg.det(cam.c2w[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(cam.K, truth.K)
    # A point 10 m in front projects inside the image, at the centre.
    uv, z = cam.project(truth.center[None] + 10 * truth.forward[None])
    assert z[0] == pytest.approx(10, abs=1e-3) and 0 <= uv[0, 0] < W and 0 <= uv[0, 1] < H
    np.testing.assert_allclose(uv[0], [W / 2, H / 2], atol=1e-2)


def test_from_matrixcity_opengl_looks_down_minus_z():
    m = np.eye(4)
    m[:3, 3] = [1.0, 2.0, 0.03]  # paper units: 100 m -> z = 3 m
    cam = from_matrixcity(m, pose_format="paper", convention="opengl", fov_deg=90, width=W, height=H)
    np.testing.assert_allclose(cam.forward, [0, 0, -1])  # NeRF camera looks down its -z
    np.testing.assert_allclose(cam.c2w[:3, 1], [0, -1, 0])  # image down = -(camera up)
    np.testing.assert_allclose(cam.center, [100, 200, 3])
    raw = np.eye(4)
    raw[:3, :3] *= 0.01
    raw[:3, 3] = [1.0, 2.0, 3.0]  # metres
    cam = from_matrixcity(raw, pose_format="raw", convention="opengl", fov_deg=90, width=W, height=H)
    np.testing.assert_allclose(cam.center, [1, 2, 3])
    np.testing.assert_allclose(cam.forward, [0, 0, -1])


def test_from_matrixcity_bad_input():
    with pytest.raises(UserError, match="not orthonormal"):  # raw rotation given to the paper format
        from_matrixcity(np.diag([0.01, 0.01, 0.01, 1]), pose_format="paper", fov_deg=90, width=W, height=H)
    with pytest.raises(UserError, match="det"):
        from_matrixcity(np.diag([1.0, 1, -1, 1]), pose_format="paper", convention="opencv", fov_deg=90,
                        width=W, height=H)
    with pytest.raises(UserError, match="expected 'raw' or 'paper'"):
        from_matrixcity(np.eye(4), pose_format="nerf", fov_deg=90, width=W, height=H)
    with pytest.raises(UserError, match="expected 'opengl' or 'opencv'"):
        from_matrixcity(np.eye(4), convention="blender", fov_deg=90, width=W, height=H)
