"""Dense stereo, fusion and disc rendering (`reference/common/geometry`) against closed forms:
a textured plane rendered exactly by ray casting, analytic depth maps, ray-disc intersection."""

import numpy as np
import pytest
import torch

from reference.common.geometry import cloud as C
from reference.common.geometry import mvs as M
from reference.common.geometry import sweep as S
from reference.common.geometry import splat
from reference.common.gaussians.project import quat_to_rotmat
from skyeyes_bench.cameras import Camera

SKY = np.array([0.6, 0.7, 0.9], np.float32)


def texture(x, y):
    """Smooth, well-textured colour on the plane (sum of sinusoids, periods 2.5-9 m)."""
    c = [0.5 + 0.2 * np.sin(0.9 * x + 0.3) * np.cos(0.7 * y) + 0.15 * np.sin(2.1 * x + 1.7 * y),
         0.5 + 0.2 * np.cos(1.3 * x - 0.4 * y) + 0.1 * np.sin(2.5 * y),
         0.5 + 0.2 * np.sin(0.8 * y + 1.1 * x) * np.sin(1.9 * x)]
    return np.clip(np.stack(c, -1), 0.05, 0.95)


def render_plane(cam: Camera, z0: float = 0.0):
    """Exact image and planar depth of the textured plane z = z0 (sky where a ray misses it)."""
    h, w = cam.height, cam.width
    v, u = np.mgrid[0:h, 0:w] + 0.5
    d_cam = np.stack([(u - cam.K[0, 2]) / cam.K[0, 0], (v - cam.K[1, 2]) / cam.K[1, 1], np.ones_like(u)], -1)
    d = d_cam @ cam.c2w[:3, :3].T
    o = cam.c2w[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (z0 - o[2]) / d[..., 2]
    hit = (d[..., 2] < -1e-9) & (t > 0)
    t = np.where(hit, t, np.nan)
    p = o + t[..., None] * d
    img = np.where(hit[..., None], texture(p[..., 0], p[..., 1]), SKY).astype(np.float32)
    return img, np.where(hit, t, np.nan).astype(np.float32)  # d_cam has z = 1: t is planar depth


def cams_along_x(xs, *, yaw=0.0, pitch=-45.0, alt=30.0, size=48, fov=70.0, y=0.0):
    return [Camera.from_ypr([x, y, alt], yaw, pitch, fov_deg=fov, width=size, height=size) for x in xs]


BOX = np.array([[-10.0, -25.0, -1.0], [60.0, 25.0, 10.0]])


@pytest.fixture
def plane_views(one_torch_thread):
    cams = cams_along_x([0.0, 6.0, 12.0, 18.0])
    rendered = [render_plane(c) for c in cams]
    return cams, [r[0] for r in rendered], [r[1] for r in rendered]


def as_tensors(images):
    return [torch.from_numpy(i).permute(2, 0, 1).float() for i in images]


def test_plane_sweep_recovers_the_depth_of_a_textured_plane(plane_views):
    cams, images, truth = plane_views
    cfg = M.MVSConfig(num_sources=3, planes=64, min_angle_deg=3.0)
    sources = M.select_sources(cams, BOX, cfg)
    assert all(sources[r] for r in range(len(cams)))
    d = M.plane_sweep(as_tensors(images), cams, 1, sources[1], BOX, cfg).numpy()
    t = truth[1]
    ok = np.isfinite(d) & np.isfinite(t)
    assert ok.mean() > 0.5
    rel = np.abs(d[ok] - t[ok]) / t[ok]
    assert np.median(rel) < 0.03, np.median(rel)
    assert (d[np.isfinite(d)] > 0).all()


def test_run_mvs_fuses_points_on_the_plane_with_closed_form_footprints(plane_views):
    cams, images, _ = plane_views
    cfg = M.MVSConfig(num_sources=3, planes=64, min_angle_deg=3.0)
    cloud, depths, stats = M.run_mvs(images, cams, BOX, cfg, max_stretch=1.0)
    assert len(cloud) > 500 and stats["points"] == len(cloud)
    for a in (cloud.xyz, cloud.rgb, cloud.normals, cloud.footprint):
        assert np.isfinite(a).all()
    # Points lie on z = 0 to within a few per cent of their distance (the plane-sweep step).
    assert np.mean(np.abs(cloud.xyz[:, 2]) < 1.0) > 0.9
    # Colours are the texture's at the fused point (the image colour of the pixel it came from).
    want = texture(cloud.xyz[:, 0], cloud.xyz[:, 1])
    assert np.median(np.abs(cloud.rgb - want)) < 0.05
    # Footprint = planar depth / focal with max_stretch = 1: recompute the depth of each point
    # in every camera; it must match one of them (the view it came from).
    f = cams[0].K[0, 0]
    z_all = np.stack([c.project(cloud.xyz.astype(np.float64))[1] for c in cams])  # [V, N]
    err = np.min(np.abs(z_all / f - cloud.footprint[None]), axis=0)
    assert np.quantile(err, 0.99) < 1e-3 * z_all.max() / f + 1e-4
    assert np.all(np.all((cloud.xyz >= BOX[0] - 1e-4) & (cloud.xyz <= BOX[1] + 1e-4), axis=1))


def test_consistency_keeps_agreeing_depths_and_drops_a_corrupted_block(one_torch_thread):
    cams = cams_along_x([0.0, 6.0, 12.0])
    truth = [torch.from_numpy(render_plane(c)[1]) for c in cams]
    bad = truth[1].clone()
    bad[10:20, 10:20] *= 1.2
    maps = [truth[0], bad, truth[2]]
    nb = [[1, 2], [0, 2], [0, 1]]
    out = M.consistency_filter(maps, cams, nb, M.MVSConfig(min_consistent=1))
    assert torch.isnan(out[1][10:20, 10:20]).all()
    finite = torch.isfinite(truth[1])
    finite[9:21, 9:21] = False
    kept = torch.isfinite(out[1]) & finite
    # Pixels that the neighbours also see (the plane's near part) are kept almost all.
    assert kept.sum() >= 0.6 * finite.sum()
    with pytest.raises(AssertionError):
        torch.testing.assert_close(out[1], bad, equal_nan=True)


def test_aggregate_sources_matches_a_slow_reference():
    rng = np.random.default_rng(0)
    c = rng.uniform(0, 2, (3, 4, 5, 6)).astype(np.float32)
    c[rng.random(c.shape) < 0.3] = np.nan
    c[:, 0, 0, 0] = np.nan  # no source at all
    for k in (1, 2, 5):
        got = S.aggregate_sources(torch.from_numpy(c), k).numpy()
        want = np.full(c.shape[1:], np.nan, np.float32)
        for idx in np.ndindex(*c.shape[1:]):
            v = np.sort(c[(slice(None),) + idx][np.isfinite(c[(slice(None),) + idx])])[:k]
            if len(v):
                want[idx] = v.mean()
        np.testing.assert_allclose(got, want, rtol=1e-6, equal_nan=True)


def test_winner_refines_to_the_vertex_of_a_sampled_parabola():
    inv = torch.linspace(0.01, 0.1, 19)
    true_inv = 0.0537
    cost = ((inv - true_inv) ** 2 * 1e3)[:, None, None].repeat(1, 2, 2)
    depth, idx = S.winner(cost, inv)
    np.testing.assert_allclose(depth.numpy(), 1 / true_inv, rtol=1e-4)
    # At the edge of the range no refinement (the vertex is not bracketed).
    cost_edge = ((inv - 0.2) ** 2)[:, None, None]
    d_edge, i_edge = S.winner(cost_edge, inv)
    assert int(i_edge) == 18 and float(d_edge) == pytest.approx(1 / 0.1)


def test_sgm_identity_without_paths_and_constant_volume_stays_constant():
    c = torch.rand(8, 5, 7)
    assert torch.equal(S.sgm(c, 0.1, 0.5, 0), c)
    const = torch.full((8, 5, 7), 0.3)
    torch.testing.assert_close(S.sgm(const, 0.1, 0.5, 4), const)
    # A single clear minimum per pixel survives aggregation where all pixels agree.
    v = torch.ones(8, 5, 7)
    v[3] = 0.0
    assert (S.sgm(v, 0.05, 0.4, 4).argmin(0) == 3).all()
    with pytest.raises(ValueError):
        S.sgm(c, 0.1, 0.5, 8)


# --------------------------------------------------------------------------- stiff cases


def test_views_with_no_overlap_give_no_sources_no_depth_and_an_empty_cloud(one_torch_thread):
    # Two cameras back to back, far apart, each looking away from the other and from the box.
    cams = [Camera.from_ypr([-100.0, 0, 30], 180.0, -45.0, fov_deg=60, width=32, height=32),
            Camera.from_ypr([200.0, 0, 30], 0.0, -45.0, fov_deg=60, width=32, height=32)]
    imgs = [render_plane(c)[0] for c in cams]
    box = np.array([[-20.0, -20, -1], [20.0, 20, 10]])
    cfg = M.MVSConfig()
    assert M.select_sources(cams, box, cfg) == [[], []]
    assert M.depth_range(cams[0], box) is None
    d = M.plane_sweep(as_tensors(imgs), cams, 0, [], box, cfg)
    assert torch.isnan(d).all()
    cloud, depths, stats = M.run_mvs(imgs, cams, box, cfg)
    assert len(cloud) == 0 and stats["views_without_sources"] == 2 and stats["points"] == 0
    assert all(np.isnan(x).all() for x in depths)


def test_shared_centres_are_never_sources():
    cams = [Camera.from_ypr([0.0, 0, 30], yaw, -45.0, fov_deg=90, width=32, height=32) for yaw in (0, 20, 40)]
    assert M.select_sources(cams, BOX, M.MVSConfig()) == [[], [], []]


def test_grazing_views_give_positive_depth_or_none(one_torch_thread):
    cams = cams_along_x([0.0, 4.0, 8.0], pitch=-3.0, alt=2.0, size=40)
    imgs = [render_plane(c)[0] for c in cams]
    box = np.array([[0.0, -20, -1], [200.0, 20, 5]])
    cfg = M.MVSConfig(num_sources=2, planes=32, min_angle_deg=0.5)
    cloud, depths, _ = M.run_mvs(imgs, cams, box, cfg)
    for d in depths:
        f = d[np.isfinite(d)]
        assert (f > 0).all() and np.isfinite(f).all()
        assert not np.isinf(d).any()
    assert np.isfinite(cloud.xyz).all() and np.isfinite(cloud.footprint).all()


def test_a_lane_that_sees_only_roofs_renders_nothing_below_the_horizon(one_torch_thread):
    """Aerial views of a roof plane at z = 20 only: the fused cloud lies on the roof, and a
    ground camera under it looking level covers nothing below the horizon."""
    cams = cams_along_x([0.0, 6.0, 12.0, 18.0], alt=45.0)
    imgs = [render_plane(c, z0=20.0)[0] for c in cams]
    box = np.array([[-10.0, -25.0, -1.0], [60.0, 25.0, 30.0]])
    cloud, _, _ = M.run_mvs(imgs, cams, box, M.MVSConfig(num_sources=3, planes=64, min_angle_deg=3.0),
                            max_stretch=1.0)
    assert len(cloud) > 100
    assert np.mean(np.abs(cloud.xyz[:, 2] - 20.0) < 1.0) > 0.9
    ground = Camera.from_ypr([25.0, 0.0, 2.0], 0.0, 0.0, fov_deg=90, width=32, height=32)
    colour, alpha = splat.render_cloud(splat.surfels(splat.voxel_downsample(cloud, 0.5)), ground)
    assert np.isfinite(colour).all()
    assert alpha[16:].max() < 0.05  # rows below the principal point look down: no roof there
    assert alpha[:16].max() > 0.5  # the roof overhead is seen above the horizon


def test_an_empty_cloud_renders_exactly_the_background():
    empty = C.PointCloud.empty()
    assert len(splat.voxel_downsample(empty, 0.5)) == 0
    params = splat.surfels(empty)
    cam = Camera.from_ypr([0.0, 0, 2], 0.0, 0.0, fov_deg=90, width=16, height=12)
    colour, alpha = splat.render_cloud(params, cam)
    assert colour.shape == (12, 16, 3) and alpha.shape == (12, 16)
    assert (alpha == 0).all() and np.isfinite(colour).all()
    bg = np.random.default_rng(1).random((12, 16, 3)).astype(np.float32)
    np.testing.assert_array_equal(splat.over(colour, alpha, bg), bg)
    assert C.ground_height(empty) is None and splat.ground_colour(empty) is None
    assert len(C.snap_to_plane(empty, (np.array([0, 0, 1.0]), 0.0), 2.0)) == 0


# --------------------------------------------------------------------------- discs and rendering


def test_disc_rotations_take_z_to_the_normal():
    rng = np.random.default_rng(2)
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n = np.concatenate([n, [[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0]]])
    R = quat_to_rotmat(torch.from_numpy(splat.disc_rotations(n)).double()).numpy()
    np.testing.assert_allclose(R[:, :, 2], n, atol=1e-6)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-6)
    R0 = quat_to_rotmat(torch.from_numpy(splat.disc_rotations(np.zeros((1, 3))))).numpy()[0]
    np.testing.assert_allclose(R0, np.eye(3), atol=1e-7)


def test_voxel_downsample_matches_a_dict_reference():
    rng = np.random.default_rng(3)
    n = 400
    xyz = rng.uniform(-2, 2, (n, 3)).astype(np.float32)
    nrm = rng.normal(size=(n, 3)).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    cloud = C.PointCloud(xyz, rng.random((n, 3)).astype(np.float32), nrm, rng.uniform(0.1, 2, n).astype(np.float32))
    voxel = 0.7
    got = splat.voxel_downsample(cloud, voxel)
    groups: dict = {}
    for i in range(n):
        groups.setdefault(tuple(np.floor(xyz[i] / voxel).astype(int)), []).append(i)
    assert len(got) == len(groups)
    by_key = {tuple(np.floor(p / voxel + 1e-9).astype(int)): j for j, p in enumerate(got.xyz.astype(np.float64))}
    for key, idx in groups.items():
        j = by_key[key]
        np.testing.assert_allclose(got.xyz[j], xyz[idx].mean(0), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(got.rgb[j], cloud.rgb[idx].mean(0), rtol=1e-5, atol=1e-6)
        assert got.footprint[j] == pytest.approx(max(cloud.footprint[idx].mean(), voxel), rel=1e-5)
        m = nrm[idx].mean(0)
        if np.linalg.norm(m) > 1e-6:
            np.testing.assert_allclose(got.normals[j], m / np.linalg.norm(m), atol=1e-5)


def _ray_disc_reference(cam, discs, inner_scale, outer_scale):
    """Per pixel, by ray-plane intersection: the colour of the nearest disc hit within
    inner_scale * r of its centre; `clean` where that hit is not within outer_scale * r of any
    nearer disc (whose soft edge could blend in); `hit_any` where any disc is within outer_scale."""
    h, w = cam.height, cam.width
    v, u = np.mgrid[0:h, 0:w] + 0.5
    d = np.stack([(u - cam.K[0, 2]) / cam.K[0, 0], (v - cam.K[1, 2]) / cam.K[1, 1], np.ones_like(u)], -1)
    d = d @ cam.c2w[:3, :3].T
    o = cam.c2w[:3, 3]
    ts, rs = [], []
    for c, n, r, _ in discs:
        t = ((c - o) @ n) / (d @ n)
        p = o + t[..., None] * d
        ts.append(np.where(t > 0, t, np.inf))
        rs.append(np.linalg.norm(p - c, axis=-1) / r)
    ts, rs = np.stack(ts), np.stack(rs)
    inner = np.where(rs <= inner_scale, ts, np.inf)
    k = inner.argmin(0)
    hit = np.isfinite(inner.min(0))
    col = np.array([x[3] for x in discs])[k]
    near_tail = np.zeros_like(hit)
    for j in range(len(discs)):
        near_tail |= (rs[j] <= outer_scale) & (ts[j] < np.take_along_axis(ts, k[None], 0)[0]) & (j != k)
    return col, hit & ~near_tail, (rs <= outer_scale).any(0)


def test_render_cloud_is_a_z_buffer_of_the_discs(one_torch_thread):
    cam = Camera.from_ypr([0.0, 0.0, 2.0], 0.0, 0.0, fov_deg=90, width=128, height=128)
    # Discs facing the camera (normal -x), at 10 m and 14 m, overlapping on screen; one off to the side.
    discs = [(np.array([10.0, 0.5, 2.0]), np.array([-1.0, 0, 0]), 1.5, np.array([0.9, 0.1, 0.1])),
             (np.array([14.0, -1.0, 2.5]), np.array([-1.0, 0, 0]), 2.5, np.array([0.1, 0.8, 0.2])),
             (np.array([12.0, 8.0, 1.0]), np.array([-1.0, 0, 0]), 2.0, np.array([0.2, 0.2, 0.9]))]
    cloud = C.PointCloud(np.array([c for c, *_ in discs], np.float32), np.array([x[3] for x in discs], np.float32),
                         np.array([x[1] for x in discs], np.float32), np.array([2 * x[2] for x in discs], np.float32))
    colour, alpha = splat.render_cloud(splat.surfels(cloud, size=1.0), cam, opacity=0.98)
    # Gaussian discs of scale s = r (q = dist^2 / s^2): alpha = 0.98 exp(-q/2) is 0.65 at 0.9 s,
    # 0.95 at 0.25 s and 0.009 at 3.1 s. Coverage: clear insides and outsides.
    _, inside, anywhere = _ray_disc_reference(cam, discs, 0.9, 3.1)
    assert inside.sum() > 300
    assert alpha[inside].min() > 0.6
    assert alpha[~anywhere].max() < 0.01
    # Colour where the nearest disc is nearly opaque (< 0.25 s): that disc's, also where the near
    # red disc hides the far green one (a z-buffer, not a blend of the two).
    col, core, _ = _ray_disc_reference(cam, discs, 0.25, 3.1)
    np.testing.assert_allclose(colour[core], col[core], atol=0.06)
    for rgb in (discs[0][3], discs[2][3]):  # the green core lies in the red disc's soft edge
        assert (core & (np.abs(col - rgb).sum(-1) < 1e-6)).sum() > 10
    red_core = core & (np.abs(col - discs[0][3]).sum(-1) < 1e-6)
    _, green_all, _ = _ray_disc_reference(cam, [discs[1]], 0.9, 3.1)
    assert (red_core & green_all).sum() > 10  # red in front of green there


def test_street_height_and_snap_against_closed_forms():
    rng = np.random.default_rng(4)
    street = np.c_[rng.uniform(0, 50, (3000, 2)), rng.normal(0.3, 0.4, 3000)]
    roofs = np.c_[rng.uniform(0, 50, (2500, 2)), rng.choice([8.0, 12.0, 21.0], 2500)]
    walls = np.c_[rng.uniform(0, 50, (2000, 2)), rng.uniform(0, 25, 2000)]
    below = np.array([[5.0, 5.0, -4.0]])
    xyz = np.concatenate([street, roofs, walls, below]).astype(np.float32)
    n = len(xyz)
    cloud = C.PointCloud(xyz, np.zeros((n, 3), np.float32), np.tile([1.0, 0, 0], (n, 1)).astype(np.float32),
                         np.ones(n, np.float32))
    z0 = C.ground_height(cloud)
    assert abs(z0 - 0.3) < 0.15
    snapped = C.snap_to_plane(cloud, (np.array([0, 0, 1.0]), z0), 2.0)
    assert len(snapped) == n - 1  # only the point 4 m under the street is dropped
    kept = np.abs(xyz[:, 2] - z0) <= 2.0
    keep_mask = xyz[:, 2] - z0 >= -2.0
    sx = snapped.xyz
    src = xyz[keep_mask]
    on = kept[keep_mask]
    np.testing.assert_allclose(sx[on, 2], z0, atol=1e-5)
    np.testing.assert_allclose(sx[on, :2], src[on, :2])
    np.testing.assert_array_equal(sx[~on], src[~on])
    np.testing.assert_allclose(snapped.normals[on], np.tile([0, 0, 1.0], (on.sum(), 1)))


def test_street_height_lies_under_the_ground_cameras():
    """A sparse cloud whose densest low layer is at the cameras' eye level (SynthTown smoke's
    stereo): the street is the mode under the cameras, or none when nothing lies under them."""
    rng = np.random.default_rng(7)

    def cloud_of(*parts):
        xyz = np.concatenate(parts).astype(np.float32)
        n = len(xyz)
        return C.PointCloud(xyz, np.zeros((n, 3), np.float32), np.zeros((n, 3), np.float32), np.ones(n, np.float32))

    street = np.c_[rng.uniform(0, 40, (200, 2)), rng.normal(0.3, 0.1, 200)]
    eye = np.c_[rng.uniform(0, 40, (800, 2)), rng.normal(1.9, 0.05, 800)]
    roofs = np.c_[rng.uniform(0, 40, (1000, 2)), rng.choice([8.0, 14.0], 1000)]
    ceiling = C.street_ceiling([2.0, 2.0, 2.4])
    assert ceiling == 1.5
    assert abs(C.ground_height(cloud_of(street, eye, roofs)) - 1.9) < 0.15  # the failure it guards against
    assert abs(C.ground_height(cloud_of(street, eye, roofs), below=ceiling) - 0.3) < 0.15
    assert C.ground_height(cloud_of(eye, roofs), below=ceiling) is None  # no street found: no prior
    assert C.ground_height(cloud_of(street[:5], eye), below=ceiling) is None  # 5 points are not a street
    assert C.street_ceiling([]) is None
