"""bench/flow_accuracy.py's geometry (the ways docs/skyeyes.md's "What moves the frames" measures),
against closed forms: a flow made rigid with the poses, and the ground plane's depth; and its
command line: it reads the validation split only (`reference.screen`)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from builders.bench_scripts import BENCH, load_bench

from skyeyes_bench.cameras import Camera, intrinsics
from skyeyes_bench.metrics.geometry import warp_coords


@pytest.fixture(scope="module")
def fa():
    return load_bench("flow_accuracy")


def _level(x: float = 0.0, z: float = 2.0, size: int = 32) -> Camera:
    """A ground camera (OpenCV axes) at height z looking level along world +y, moved x metres
    along it: camera x = world x, camera y (down) = world -z, camera z (ahead) = world y."""
    c2w = np.eye(4)
    c2w[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]
    c2w[:3, 3] = [0.0, x, z]
    return Camera(intrinsics(60.0, size, size), c2w, size, size)


def test_ground_filled_is_the_plane_below_the_horizon_and_keeps_what_is_nearer(fa):
    """A camera 2 m above the plane z = 0: pixel row v below the principal point meets it at
    planar depth 2 f / (v - cy); rows at or above the horizon keep their depth (+inf stays)."""
    cam = _level()
    f, cy = cam.K[1, 1], cam.K[1, 2]
    v = np.arange(32) + 0.5
    depth = np.full((32, 32), np.inf)
    depth[30, 5] = 1.0  # something nearer than the road
    out = fa.ground_filled(depth, cam, 0.0)
    below = v > cy
    want = np.where(below, 2.0 * f / np.where(below, v - cy, 1.0), np.inf)[:, None].repeat(32, 1)
    want[30, 5] = 1.0
    np.testing.assert_allclose(out, want, rtol=1e-12)


def test_rigid_from_flow_recovers_a_rigid_motion_and_drops_what_leaves_the_epipolar_line(fa):
    """Driving 0.5 m ahead over the plane z = 0 with a wall at y = 10 m: given the exact
    correspondence (`warp_coords` of the true depths) `rigid_from_flow` returns it to within the
    depth grid's quantisation; noise across the epipolar lines (for a forward move, the lines
    through the principal point) falls to a fraction; an outlier along its line too (which no depth
search removes) is put back by the median of its neighbours' depths."""
    size = 32
    cams = [_level(0.0, size=size), _level(0.5, size=size)]
    depths = [fa.ground_filled(np.full((size, size), 10.0 - x), c, 0.0) for x, c in ((0.0, cams[0]), (0.5, cams[1]))]
    truth, ok = warp_coords(depths[1], cams[1], depths[0], cams[0], 0.01)
    u = np.arange(size) + 0.5
    xs, ys = np.meshgrid(u, u)
    centre = cams[1].K[:2, 2]
    ok &= np.hypot(xs - centre[0], ys - centre[1]) > 3  # no epipolar direction at the centre
    truth = np.nan_to_num(truth)
    motion = np.hypot(truth[..., 0] - xs, truth[..., 1] - ys)
    uv, _ = fa.rigid_from_flow(truth, ok, cams[1], cams[0], median_px=1)
    err = np.hypot(*(uv - truth)[ok].T)
    assert np.all(err <= 0.03 * motion[ok] + 1e-6), (err.max(), motion[ok].max())
    radial = truth - centre
    normal = np.stack([-radial[..., 1], radial[..., 0]], -1) / np.linalg.norm(radial, axis=-1, keepdims=True)
    noise = np.random.default_rng(0).normal(0.0, 0.7, (size, size))[..., None] * normal
    uv, _ = fa.rigid_from_flow(truth + noise, ok, cams[1], cams[0], median_px=1)
    assert np.hypot(*(uv - truth)[ok].T).mean() < 0.25 * np.hypot(*noise[ok].T).mean()
    bad = truth.copy()
    bad[6, 24] += 4.0 * normal[6, 24] + 3.0 * radial[6, 24] / np.linalg.norm(radial[6, 24])  # along its line too
    uv, _ = fa.rigid_from_flow(bad, ok, cams[1], cams[0], median_px=3)
    assert np.hypot(*(uv[6, 24] - truth[6, 24])) < 0.1 * np.hypot(*(bad[6, 24] - truth[6, 24]))


def _script(*args: str) -> subprocess.CompletedProcess:
    """bench/flow_accuracy.py run as a user runs it (its own process, from the repository root)."""
    return subprocess.run([sys.executable, str(BENCH / "flow_accuracy.py"), *args], capture_output=True, text=True,
                          cwd=BENCH.parent, timeout=300)


def test_flow_accuracy_refuses_the_test_split_in_one_line(tmp_path):
    """Its flow's constants are chosen on what it measures, so `--split test` exits 2 with one line
    (no traceback) before it opens any data; `--help` lists the screen's options and its own."""
    r = _script("--split", "test", "--data", str(tmp_path / "absent"), "--priors", str(tmp_path), "--prior",
                str(tmp_path))
    assert r.returncode == 2, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "validation split" in r.stderr and "Traceback" not in r.stderr
    h = _script("--help")
    assert h.returncode == 0, h.stderr
    for option in ("--split", "--data", "--scenes", "--priors", "--prior", "--ways", "--fb-px"):
        assert option in h.stdout
