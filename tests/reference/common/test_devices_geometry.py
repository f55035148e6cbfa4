"""Issue 34, the geometry side: every tensor is made on the device of the data it works with.

Each component runs on CPU inputs inside `stray_device()` (a tensor that project code makes
without naming a device lands on `meta` there, so mixing it with the data fails on this CPU as
it would on CUDA) and must (a) not raise, (b) leave its outputs on the CPU, (c) equal, exactly,
the same call made outside the mode: the explicit devices change nothing on the CPU, where the
committed leaderboard rows were computed. It must also (d) make no device-less tensor at all
(`mode.sites` is empty), so a stray one that happens never to meet the data is caught too.

The numerics on a real GPU are `test_gpu_geometry.py`'s (marked `gpu`). The builders below
(`gaussian_scene`, `plane_views`, ...) are shared with it.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from builders.devices import assert_on, stray_device
from skyeyes_bench.cameras import Camera

pytestmark = pytest.mark.usefixtures("one_torch_thread")


# --------------------------------------------------------------------------- builders


def gaussian_scene(n: int, *, dtype=torch.float32, seed: int = 0, sh_bases: int = 4, opaque: bool = False,
                   device="cpu") -> list[torch.Tensor]:
    """Random Gaussians in front of the identity camera: means [N, 3], quats [N, 4], scales [N, 3],
    opacities [N], sh [N, K, 3], leaves with grad, drawn on the CPU (the same scene for every
    device) and moved to `device`. opaque: stacked, nearly opaque Gaussians (opacity 0.995: the
    0.99 clamp, the 1e-4 early stop and the backward's clamp mask are all exercised)."""
    g = torch.Generator().manual_seed(seed)
    cpu = torch.device("cpu")
    means = torch.randn(n, 3, generator=g, dtype=dtype, device=cpu) * torch.tensor([1.0, 1.0, 0.5], dtype=dtype,
                                                                                   device=cpu)
    means[:, 2] += 5.0
    quats = torch.randn(n, 4, generator=g, dtype=dtype, device=cpu)
    scales = torch.rand(n, 3, generator=g, dtype=dtype, device=cpu) * 0.2 + 0.02
    opac = torch.rand(n, generator=g, dtype=dtype, device=cpu) * 0.9 + 0.05
    sh = torch.randn(n, sh_bases, 3, generator=g, dtype=dtype, device=cpu) * 0.3
    if opaque:
        opac = torch.full_like(opac, 0.995)
        scales = scales * 3
    return [t.to(device).requires_grad_() for t in (means, quats, scales, opac, sh)]


def camera(size: int = 24, *, dtype=torch.float32, device="cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """(viewmat [4, 4] identity, K [3, 3]) of a square camera looking down +z."""
    K = torch.tensor([[size * 0.8, 0, size / 2], [0, size * 0.8, size / 2], [0, 0, 1.0]], dtype=dtype, device=device)
    return torch.eye(4, dtype=dtype, device=device), K


def image_loss(out: dict, seed: int = 1) -> torch.Tensor:
    """A scalar that weighs every pixel of rgb, depth and alpha differently (random weights drawn
    in float32 on the CPU, then moved to the render's device and dtype: the same for all)."""
    g = torch.Generator().manual_seed(seed)
    h, w = out["alpha"].shape
    dev, dt = out["rgb"].device, out["rgb"].dtype
    wr, wd, wa = (torch.randn(*s, generator=g, device="cpu").to(dev, dt) for s in ((h, w, 3), (h, w), (h, w)))
    return (out["rgb"] * wr).sum() + 0.1 * (out["depth"] * wd).sum() + (out["alpha"] * wa).sum()


def texture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Smooth, well-textured colour [..., 3] on the ground plane (sinusoids, periods 2.5-9 m)."""
    c = [0.5 + 0.2 * np.sin(0.9 * x + 0.3) * np.cos(0.7 * y) + 0.15 * np.sin(2.1 * x + 1.7 * y),
         0.5 + 0.2 * np.cos(1.3 * x - 0.4 * y) + 0.1 * np.sin(2.5 * y),
         0.5 + 0.2 * np.sin(0.8 * y + 1.1 * x) * np.sin(1.9 * x)]
    return np.clip(np.stack(c, -1), 0.05, 0.95)


def render_plane(cam: Camera) -> np.ndarray:
    """Exact float32 image [H, W, 3] of the textured plane z = 0 (sky colour where a ray misses it)."""
    v, u = np.mgrid[0:cam.height, 0:cam.width] + 0.5
    d = np.stack([(u - cam.K[0, 2]) / cam.K[0, 0], (v - cam.K[1, 2]) / cam.K[1, 1], np.ones_like(u)], -1)
    d = d @ cam.c2w[:3, :3].T
    o = cam.c2w[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[2] / d[..., 2]
    hit = (d[..., 2] < -1e-9) & (t > 0)
    p = o + np.where(hit, t, 0.0)[..., None] * d
    return np.where(hit[..., None], texture(p[..., 0], p[..., 1]), [0.6, 0.7, 0.9]).astype(np.float32)


#: The region of `plane_views` (x along the cameras' line, y across it, z up; m).
PLANE_BOX = np.array([[-10.0, -25.0, -1.0], [60.0, 25.0, 10.0]])


def plane_views(size: int = 32) -> tuple[list[Camera], list[np.ndarray]]:
    """Four aerial cameras in a row at 30 m looking 45 deg down at the textured plane, and their images."""
    cams = [Camera.from_ypr([x, 0.0, 30.0], 0.0, -45.0, fov_deg=70.0, width=size, height=size)
            for x in (0.0, 6.0, 12.0, 18.0)]
    return cams, [render_plane(c) for c in cams]


def ground_camera(size: int = 24) -> Camera:
    """A ground-level camera inside `PLANE_BOX` looking along the street, slightly down."""
    return Camera.from_ypr([5.0, 0.0, 2.0], 0.0, -10.0, fov_deg=90.0, width=size, height=size)


#: A NeRF small enough for a few steps in well under a second.
def tiny_nerf_config():
    from reference.common.nerf import NeRFConfig

    return NeRFConfig(levels=2, log2_T=8, n_min=4, n_max=16, hidden=8, n_inner=12, n_outer=4, occ_res=8, occ_every=2,
                      occ_warmup=2, iterations=6, batch_rays=128, chunk=256)


# --------------------------------------------------------------------------- the check


def _walk_equal(a, b, path="out"):
    """a and b equal exactly (NaN equal to NaN), tensors also in dtype, shape and device."""
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor), path
        torch.testing.assert_close(b, a, rtol=0, atol=0, equal_nan=True, msg=lambda m: f"{path}: {m}")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype, path
        np.testing.assert_array_equal(b, a, err_msg=path)
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for k in a:
            _walk_equal(a[k], b[k], f"{path}[{k!r}]")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _walk_equal(x, y, f"{path}[{i}]")
    elif dataclasses.is_dataclass(a):
        _walk_equal(dataclasses.asdict(a), dataclasses.asdict(b), path)
    elif isinstance(a, float) and math.isnan(a):
        assert isinstance(b, float) and math.isnan(b), path
    else:
        assert a == b, (path, a, b)


def check_devices(fn):
    """Run fn() outside and then inside `stray_device()`; assert the four points of the module
    docstring and return the output."""
    want = fn()
    with stray_device() as mode:
        got = fn()  # (a): raises on a device-less tensor that meets the data
    assert not mode.sites, f"device-less tensors made at {sorted(set(mode.sites))}"
    assert_on("cpu", got)
    _walk_equal(want, got)
    return got


# --------------------------------------------------------------------------- Gaussians


@pytest.mark.parametrize("opaque", [False, True], ids=["random", "opaque"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_rasterizer_forward_and_backward(dtype, opaque):
    from reference.common.gaussians import rasterize

    def run():
        params = gaussian_scene(150 if opaque else 120, dtype=dtype, opaque=opaque, sh_bases=4)
        view, K = camera(dtype=dtype)
        bg = torch.tensor([0.1, 0.2, 0.3], dtype=dtype)
        out = rasterize(*params, view, K, 24, 20, background=bg, sh_degree=1, backend="torch")
        grads = torch.autograd.grad(image_loss(out), params)
        return {k: v.detach() for k, v in out.items()}, grads

    out, _ = check_devices(run)
    assert out["alpha"].max() > 0.9
    if opaque:  # the early stop happened
        assert (1 - out["alpha"]).min() < 1e-3


def test_rasterizer_parts_default_background_and_no_gaussians():
    from reference.common.gaussians import project, raster, rasterize

    def run():
        params = [p.detach() for p in gaussian_scene(40)]
        view, K = camera()
        out = rasterize(*params, view, K, 16, 12)  # default background, no gradient kept
        empty = rasterize(*(p[:0] for p in params), view, K, 8, 8)
        proj = project(*params[:3], view, K, 16, 12)
        squares = raster.bin_tiles(proj["means2d"], proj["radii"], proj["depths"], proj["valid"], 16, 12)
        ellipses = raster.bin_tiles(proj["means2d"], proj["radii"], proj["depths"], proj["valid"], 16, 12,
                                    conics=proj["conics"])  # without opacities: the support ellipses
        return out, empty, squares, ellipses

    out, empty, squares, ellipses = check_devices(run)
    assert (empty["alpha"] == 0).all() and (empty["rgb"] == 0).all()
    assert 0 < len(ellipses[0]) < len(squares[0])


def test_dense_reference_and_projection():
    from reference.common.gaussians import project, rasterize_dense
    from reference.common.gaussians.project import covariance_3d, sh_colors

    def run():
        params = gaussian_scene(30, dtype=torch.float64)
        view, K = camera(dtype=torch.float64)
        dense = rasterize_dense(*params, view, K, 12, 10)
        proj = project(params[0], params[1], params[2], view, K, 12, 10)
        colours = sh_colors(params[4], params[0], view, 1)
        grads = torch.autograd.grad(image_loss(dense) + colours.sum() + proj["means2d"].sum(), params)
        return dense, proj, colours, covariance_3d(params[1], params[2]), grads

    check_devices(run)


def test_ssim_forward_and_backward():
    from reference.common.gaussians.ssim import ssim

    def run():
        g = torch.Generator().manual_seed(0)
        a = torch.rand(20, 17, 3, generator=g).requires_grad_()
        b = torch.rand(20, 17, 3, generator=g)
        val = ssim(a, b)
        return val.detach(), torch.autograd.grad(val, a)[0]

    check_devices(run)


def _points(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 3)) * [1.0, 1.0, 0.3] + [0, 0, 5], rng.random((n, 3))


def test_gaussian_model_starts_and_densification_bookkeeping():
    from reference.common.gaussians.model import GaussianModel
    from reference.common.geometry import cloud as C
    from reference.common.geometry import splat

    def run():
        m = GaussianModel.from_points(*_points(50), sh_degree=1)
        opt = m.make_optimizer({k: 1e-3 for k in m.params})
        sum((v ** 2).sum() for v in m.params.values()).backward()
        opt.step()
        m.append(opt, m.split_values(torch.tensor([0, 3]), 2, torch.Generator().manual_seed(0)))
        keep = torch.ones(len(m), dtype=torch.bool)
        keep[[1, 2]] = False
        m.keep(opt, keep)
        xyz, rgb = _points(20, seed=1)
        cloud = C.PointCloud(xyz.astype(np.float32), rgb.astype(np.float32),
                             np.tile([0.0, 0.0, 1.0], (20, 1)).astype(np.float32), np.full(20, 0.3, np.float32))
        discs = GaussianModel.from_surfels(splat.surfels(cloud), 2)
        return m.state_dict(), {id_: opt.state[m.params[id_]]["exp_avg"] for id_ in m.params}, discs.state_dict()

    check_devices(run)


def test_gaussians_training_loop_with_sugar_regulariser():
    from reference.common.gaussians import rasterize
    from reference.common.gaussians.model import GaussianModel
    from reference.common.gaussians.sugar_reg import SugarRegularizer, SugarWeights
    from reference.common.gaussians.train import TrainConfig, View, train

    xyz, rgb = _points(60)
    truth = GaussianModel.from_points(xyz, rgb, 0, opacity=0.8)
    view, K = camera(32)
    with torch.no_grad():
        img = rasterize(truth.means, truth.quats, truth.scales, truth.opacities, truth.sh, view, K, 32, 32)["rgb"]
    mask = torch.ones(32, 32, dtype=torch.bool)
    mask[:4] = False

    def run():
        m = GaussianModel.from_points(xyz[::2], np.full((30, 3), 0.5), 1)
        # Densify, prune to the box, reset opacities, warm up SH; SuGaR's entropy then SDF terms.
        cfg = TrainConfig(iterations=12, densify_from=4, densify_until=10, densify_every=4, sh_degree=1,
                          sh_increase_every=5, densify_grad=1e-6, max_gaussians=200, opacity_reset_every=8)
        reg = SugarRegularizer(SugarWeights(entropy_from=2, sdf_from=5, samples=100, knn=4, knn_every=3))
        stats = train(m, [View(img.clamp(0, 1), view, K, mask)], cfg, extent=2.0, progress=False, regularizer=reg,
                      box=torch.tensor([[-5.0, -5, 0], [5, 5, 10]]), background=torch.tensor([0.2, 0.3, 0.4]))
        stats.pop("train_seconds")
        return m.state_dict(), stats, reg.last

    state, stats, last = check_devices(run)
    assert stats["gaussians"] != 30 and {"entropy", "sdf", "normal"} <= set(last)


def test_sugar_sdf_and_normal_terms():
    from reference.common.gaussians.model import GaussianModel
    from reference.common.gaussians.sugar_reg import sdf_terms

    def run():
        m = GaussianModel.from_points(*_points(24), 0, opacity=0.5)
        knn = (torch.arange(24)[:, None] + torch.arange(4)) % 24  # self and the next three
        sdf, normal = sdf_terms(m, knn, 200, torch.Generator().manual_seed(0))
        return sdf.detach(), normal.detach(), torch.autograd.grad(sdf + normal, m.means)[0]

    check_devices(run)


# --------------------------------------------------------------------------- MVS and discs


def test_mvs_plane_sweep_consistency_and_fusion():
    from reference.common.geometry import mvs as M
    from reference.common.geometry import sweep as S

    cams, images = plane_views()
    cfg = M.MVSConfig(num_sources=3, planes=24, min_angle_deg=3.0)

    def run():
        cloud, depths, stats = M.run_mvs(images, cams, PLANE_BOX, cfg, max_stretch=2.0)
        imgs = [torch.from_numpy(i).permute(2, 0, 1).contiguous() for i in images]
        sources = M.select_sources(cams, PLANE_BOX, cfg)
        raw = M.plane_sweep(imgs, cams, 1, sources[1], PLANE_BOX, cfg)
        none = M.plane_sweep(imgs, cams, 1, [], PLANE_BOX, cfg)
        costs = S.ncc_costs(imgs[1], imgs[2], cams[1], cams[2], torch.linspace(20.0, 60.0, 5), cfg)
        return cloud, depths, stats, raw, none, costs, M.depth_normals(cams[1], torch.nan_to_num(raw, nan=30.0))

    cloud, depths, stats, *_ = check_devices(run)
    assert len(cloud) > 200 and stats["filtered_coverage"] > 0.2


def test_surfels_street_prior_and_disc_rendering():
    from reference.common.geometry import cloud as C
    from reference.common.geometry import mvs as M
    from reference.common.geometry import region, splat

    cams, images = plane_views()
    fused, _, _ = M.run_mvs(images, cams, PLANE_BOX, M.MVSConfig(num_sources=3, planes=24, min_angle_deg=3.0))
    ground = ground_camera()

    def run():
        z0 = C.ground_height(fused, below=C.street_ceiling([2.0]))
        snapped = C.snap_to_plane(fused, (np.array([0.0, 0.0, 1.0]), z0), 2.0)
        params = splat.surfels(splat.voxel_downsample(snapped, 0.5))
        out = splat.render_surfels(params, ground, near=0.5)
        empty = splat.render_cloud(splat.surfels(C.PointCloud.empty()), ground)
        return z0, params, out, empty, region.rays_hit_box(ground, PLANE_BOX), splat.ground_colour(snapped)

    *_, out, _, _, _ = check_devices(run)
    assert out["alpha"].max() > 0.5


# --------------------------------------------------------------------------- NeRF


def test_nerf_field_encoding_and_occupancy_grid():
    from reference.common.nerf import NeRFField, OccupancyGrid, SceneBox
    from reference.common.nerf.render import composite, distortion_loss, render_weights, sample_intervals, to_unit

    cfg = tiny_nerf_config()
    box = SceneBox(PLANE_BOX[0], PLANE_BOX[1])

    def run():
        fld = NeRFField(cfg.field_config(), seed=0)
        grid = OccupancyGrid(cfg.occ_res, step_m=cfg.inner_step(box), alpha=0.01, mean_clamp=True)
        gen = torch.Generator().manual_seed(0)
        grid.update(lambda p: fld.density(p)[0], gen)  # every cell
        grid.update(lambda p: fld.density(p)[0], gen, n_cells=100)  # half uniform, half occupied
        pts = torch.tensor([[1.0, 2.0, 0.0], [20.0, -3.0, 1.0]])
        grid.mark_points(to_unit(box.normalise(pts)))
        o = torch.tensor([[5.0, 0.0, 2.0], [0.0, 0.0, 30.0]])
        d = torch.nn.functional.normalize(torch.tensor([[1.0, 0.2, -0.1], [0.3, 0.0, -1.0]]), dim=-1)
        t = sample_intervals(o, d, box, n_inner=8, n_outer=4, near=0.5, far=500.0, generator=gen)
        u = to_unit(box.normalise(o[:, None] + d[:, None] * t[:, 1:, None]))
        sig, geo = fld.density(u.reshape(-1, 3))
        rgb = fld.colour(geo, d.repeat_interleave(t.shape[1] - 1, 0))
        w, left = render_weights(sig.reshape(2, -1), t.diff(dim=1))
        loss = composite(w, rgb.reshape(2, -1, 3), torch.zeros(3))[0].sum() + distortion_loss(w).sum()
        grads = torch.autograd.grad(loss, list(fld.parameters()))
        return fld.state_dict(), grid.state_dict(), grid.occupied, grid.cell_points(torch.arange(5), gen), w, grads

    check_devices(run)


def test_nerf_training_rendering_and_baking():
    from reference.common.nerf import (Model, NeRFField, OccupancyGrid, SceneBox, bake_field, camera_rays,
                                       pretrain_density, render_baked_camera, render_camera, train)
    from reference.common.nerf.render import to_unit

    cfg = tiny_nerf_config()
    box = SceneBox(PLANE_BOX[0], PLANE_BOX[1])
    cams, images = plane_views(16)
    ground = ground_camera(12)

    def run():
        model = Model(NeRFField(cfg.field_config(), seed=0),
                      OccupancyGrid(cfg.occ_res, step_m=cfg.inner_step(box), alpha=cfg.occ_alpha), box,
                      torch.tensor([0.6, 0.7, 0.9]))
        pts = torch.tensor([[x, y, 0.0] for x in range(0, 20, 4) for y in range(-8, 9, 4)])
        model.grid.mark_points(to_unit(box.normalise(pts)))
        init_loss = pretrain_density(model, pts, cfg, steps=2, batch=64)
        stats = train(model, camera_rays(cams, images, "cpu"), cfg, progress=False, full_warmup=True)
        field = render_camera(model, ground, cfg, near=0.5)
        centres = torch.tensor([[5.0, 0.0, 2.0]])
        bakes = [bake_field(model.field, box, voxel_m=6.0, view=v, centres=centres, grid=model.grid)
                 for v in ("camera", "horizontal", "aerial")]
        baked = render_baked_camera(bakes[0], ground, n_samples=12, near=0.5)
        for k in ("train_seconds", "train_cpu_seconds", "train_rays_per_s"):
            stats.pop(k)
        bakes = [b.state_dict() for b in bakes]
        return init_loss, stats, model.field.state_dict(), model.grid.sigma, field, bakes, baked

    check_devices(run)


# --------------------------------------------------------------------------- appearance


def test_appearance_colour_map_and_backgrounds():
    from reference.common.appearance import AppearanceFit, Backgrounds, ColourMap

    cams, images = plane_views(16)
    ground = ground_camera(16)

    def run():
        fit = AppearanceFit(max_pixels=300)
        for img in images:
            alpha = np.linspace(0, 1, img.shape[0] * img.shape[1]).reshape(img.shape[:2])
            fit.add(img, alpha, np.clip(img * 0.9 + 0.05, 0, 1), ground)
        cmap, bgs = fit.result(np.full(3, 0.5), np.full(3, 0.4))
        again = Backgrounds.from_dict(bgs.to_dict())
        return cmap.coef, cmap(images[0]), ColourMap.from_dict(cmap.to_dict()).coef, again.image(ground)

    check_devices(run)


# --------------------------------------------------------------------------- methods end to end

#: Reduced smoke runs: a few training steps, one train lane for the learned appearance (its
#: renders go through the disc renderer too). A fit and the render of one sequence took 3-6 s
#: here (the nerf one the longest), under load; the test runs each twice.
FAST = {
    "mvs": dict(train_lanes=1),
    "gaussians3d": dict(iterations=12, densify_from=4, densify_until=10, densify_every=4, train_lanes=1),
    "sugar": dict(iterations=12, densify_from=4, densify_until=10, densify_every=4, train_lanes=1, sdf_samples=200),
    "nerf": dict(iterations=8, occ_warmup=4, train_lanes=1, init="mvs", init_steps=3),
    "mean-frame": dict(),
}


def fit_and_render(name: str, dataset_root: Path, workdir: Path, *, device: str = "cpu", **extra) -> np.ndarray:
    """Fit the smoke preset of method `name` (`FAST`'s reduced schedule) on the first test scene
    of the dataset and render its first sequence: float32 [F, H, W, 3]. No worker processes.
    `device`: the config's, for methods that have one (mean-frame has no tensors)."""
    from reference.method import has_field
    from reference.methods import get_method_class
    from skyeyes_bench.data.layout import open_dataset

    ds = open_dataset(dataset_root)
    scene = ds.split("test")[0]
    cls = get_method_class(name)
    values = {**FAST[name], **extra}
    if has_field(cls.presets["smoke"], "device"):
        values["device"] = device
    m = cls.from_preset("smoke", workdir, progress=False, **values)
    m.jobs = 1
    m.fit_train(ds)
    m.fit_scene(scene, progress=False)
    seq = next(iter(scene.sequences.values()))
    return np.stack(list(m.render_sequence(scene, seq)))


@pytest.mark.parametrize("name", ["mvs", "gaussians3d", "sugar", "nerf", "mean-frame"])
def test_method_fits_and_renders_without_stray_tensors(name, synthtown_smoke, tmp_path):
    want = fit_and_render(name, synthtown_smoke, tmp_path / "outside")
    with stray_device() as mode:
        got = fit_and_render(name, synthtown_smoke, tmp_path / "inside")
    assert not mode.sites, f"device-less tensors made at {sorted(set(mode.sites))}"
    assert got.dtype == np.float32 and np.isfinite(got).all() and got.min() >= 0 and got.max() <= 1
    np.testing.assert_array_equal(got, want)
