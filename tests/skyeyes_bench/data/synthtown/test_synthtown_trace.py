"""SynthTown ray casting: grid traversal against brute force, analytic depths, degenerate rays."""

import numpy as np
import pytest

from skyeyes_bench.cameras import Camera
from skyeyes_bench.data.synthtown import town as tw
from skyeyes_bench.data.synthtown.render import BUILDING, SKY, Scene, render
from skyeyes_bench.data.synthtown.trace import build_grid, ground_hit, trace, trace_brute


@pytest.fixture(scope="module")
def small_town():
    return tw.make_town("train-0", 0, (2, 2))


def _trace_both(town, o, d, limit, cell=8.0):
    grid = build_grid(town.box_lo, town.box_hi, town.ell_centre, town.ell_radii, cell)
    t_fast, p_fast = trace(grid, town.box_lo, town.box_hi, town.ell_centre, town.ell_radii, o, d, limit)
    t_slow, p_slow = trace_brute(town.box_lo, town.box_hi, town.ell_centre, town.ell_radii, o, d, limit)
    return t_fast, p_fast, t_slow, p_slow


@pytest.mark.parametrize("cell", [5.0, 8.0, 13.0])
def test_grid_trace_matches_brute_force(small_town, cell):
    rng = np.random.default_rng(1)
    n = 3000
    x0, y0, x1, y1 = small_town.extent
    # Street-level and aerial origins, directions from all over the sphere.
    o = np.stack([rng.uniform(x0 - 20, x1 + 20, n), rng.uniform(y0 - 20, y1 + 20, n),
                  np.where(rng.random(n) < 0.5, rng.uniform(0.2, 3.0, n), rng.uniform(20, 80, n))], axis=1)
    d = rng.normal(size=(n, 3))
    limit = np.minimum(ground_hit(o, d), 400.0 / np.linalg.norm(d, axis=1))
    t_fast, p_fast, t_slow, p_slow = _trace_both(small_town, o, d, limit, cell)
    assert np.array_equal(np.isfinite(t_fast), np.isfinite(t_slow))
    fin = np.isfinite(t_slow)
    assert fin.mean() > 0.2  # the sample does hit things
    np.testing.assert_allclose(t_fast[fin], t_slow[fin], rtol=1e-12, atol=1e-9)
    # Same primitive, except for exact ties (coplanar faces), where the distances already agree.
    assert (p_fast[fin] == p_slow[fin]).mean() > 0.999


def test_axis_parallel_rays_and_rays_in_face_planes():
    """Directions with exact zero components, origins exactly in face planes: no NaN, same as brute force."""
    town = tw.from_boxes([[0, 0, 0], [10, -5, 0]], [[4, 4, 6], [14, 5, 12]])
    o, d = [], []
    for z in (0.0, 2.0, 6.0, 12.0):  # z = 6, 12: exactly in a top-face plane
        for y in (-5.0, 0.0, 2.0, 4.0, 5.0):  # y = 0, 4, -5, 5: exactly in side-face planes
            for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1)):
                o.append((-3.0, y, z))
                d.append((dx, dy, 0.0))
    o, d = np.array(o), np.array(d)
    limit = np.minimum(ground_hit(o, d), 1e3)
    t_fast, p_fast, t_slow, p_slow = _trace_both(town, o, d, limit)
    assert not np.isnan(t_fast).any()
    np.testing.assert_array_equal(t_fast, t_slow)
    # A ray along x at y = 2, z = 2 meets the first box's face x = 0 at t = 3.
    k = np.nonzero((o[:, 1] == 2) & (o[:, 2] == 2) & (d[:, 0] == 1) & (d[:, 1] == 0))[0][0]
    assert t_fast[k] == 3.0 and p_fast[k] == 0


@pytest.mark.parametrize("dist", [0.5, 3.0, 17.25, 80.0])
def test_depth_of_a_wall_is_the_analytic_distance(dist):
    """Camera facing a wall (face x = 0) from x = -dist: planar depth = dist on every wall pixel."""
    town = tw.from_boxes([[0, -500, 0]], [[5, 500, 400]])
    scene = Scene.from_town(town, cull_m=1000.0)
    cam = Camera.from_ypr([-dist, 3.0, 10.0], 0.0, 0.0, fov_deg=90, width=40, height=30)
    rgb, depth, labels = render(scene, cam, aa=1)
    wall = labels == BUILDING
    assert wall.sum() > 0.5 * wall.size
    np.testing.assert_allclose(depth[wall], dist, rtol=1e-6)  # float32 storage
    # Pixels below the wall see the ground plane at z = 0: planar depth from the pinhole model.
    assert np.isfinite(rgb).all()


def test_ellipsoid_depth_matches_sphere_formula():
    """A sphere of radius r at distance D straight ahead: depth at the centre pixel is D - r."""
    town = tw.from_boxes(np.zeros((0, 3)), np.zeros((0, 3)), ellipsoids=([[30.0, 0, 50]], [[4.0, 4.0, 4.0]]))
    scene = Scene.from_town(town, cull_m=1000.0)
    cam = Camera.from_ypr([0.0, 0.0, 50.0], 0.0, 0.0, fov_deg=60, width=31, height=31)
    _, depth, labels = render(scene, cam, aa=1)
    assert depth[15, 15] == pytest.approx(26.0, rel=1e-6)
    # Every vegetation pixel's ray meets the sphere: |o + t d - c| = r with t = planar depth.
    uv = cam.pixel_centers()
    pts = cam.unproject(uv, depth.reshape(-1).astype(np.float64).clip(max=1e9))
    veg = labels.reshape(-1) == 6
    r = np.linalg.norm(pts[veg] - [30.0, 0, 50], axis=1)
    np.testing.assert_allclose(r, 4.0, rtol=1e-5)


def test_camera_inside_a_building_and_on_a_face():
    """Inside: every pixel sees the building's inner faces (finite depth, no NaN, no sky). On a face
    looking out: the building is not seen. On a face looking in: the far wall."""
    town = tw.from_boxes([[0, 0, 0]], [[20, 10, 30]])
    scene = Scene.from_town(town, cull_m=500.0)
    for yaw, pitch in ((0, 0), (90, 30), (200, -60), (0, 90)):
        cam = Camera.from_ypr([5.0, 5.0, 10.0], yaw, pitch, fov_deg=90, width=24, height=24)
        rgb, depth, labels = render(scene, cam, aa=2)
        assert np.isfinite(rgb).all() and np.isfinite(depth).all()
        assert (labels != SKY).all()
    # Exactly on the face x = 0, looking out (-x): nothing of the building in view.
    out = Camera.from_ypr([0.0, 5.0, 10.0], 180.0, 0.0, fov_deg=60, width=24, height=24)
    _, d_out, l_out = render(scene, out, aa=1)
    assert not np.isin(l_out, [4, 5]).any()
    # On the face looking in (+x): the inner side of the far wall x = 20, planar depth 20.
    inn = Camera.from_ypr([0.0, 5.0, 10.0], 0.0, 0.0, fov_deg=30, width=8, height=8)
    _, d_in, _ = render(scene, inn, aa=1)
    np.testing.assert_allclose(d_in, 20.0, rtol=1e-6)
