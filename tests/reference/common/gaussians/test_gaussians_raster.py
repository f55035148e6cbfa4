"""Tile rasterizer vs its dense reference (forward, backward, gradcheck), projection and SH
against independent computations, and stiff cases (no NaN/Inf anywhere)."""

import importlib
import math

import numpy as np
import pytest
import torch

from reference.common.gaussians import project, rasterize, rasterize_dense
from reference.common.gaussians import raster
from reference.common.gaussians.project import BLUR_PX2, eval_sh
from skyeyes_bench.cameras import Camera


def _scene(n, dtype=torch.float32, seed=0, z=5.0, sh_bases=4):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([1.0, 1.0, 0.5], dtype=dtype)
    means[:, 2] += z
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.2 + 0.02
    opac = torch.rand(n, generator=g, dtype=dtype) * 0.9 + 0.05
    sh = torch.randn(n, sh_bases, 3, generator=g, dtype=dtype) * 0.3
    return [t.requires_grad_() for t in (means, quats, scales, opac, sh)]


def _cam(size=24, dtype=torch.float32):
    K = torch.tensor([[size * 0.8, 0, size / 2], [0, size * 0.8, size / 2], [0, 0, 1.0]], dtype=dtype)
    return torch.eye(4, dtype=dtype), K


def _loss(out, seed=1):
    g = torch.Generator().manual_seed(seed)
    h, w = out["alpha"].shape
    wr = torch.randn(h, w, 3, generator=g, dtype=out["rgb"].dtype)
    wd = torch.randn(h, w, generator=g, dtype=out["rgb"].dtype)
    wa = torch.randn(h, w, generator=g, dtype=out["rgb"].dtype)
    return (out["rgb"] * wr).sum() + 0.1 * (out["depth"] * wd).sum() + (out["alpha"] * wa).sum()



pytestmark = pytest.mark.usefixtures("one_torch_thread")

@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-9), (torch.float32, 2e-4)])
@pytest.mark.parametrize("sh_bases", [1, 16])
def test_matches_dense_reference_forward_and_backward(dtype, tol, sh_bases):
    params = _scene(120, dtype, sh_bases=sh_bases)
    view, K = _cam(dtype=dtype)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=dtype)
    fast = rasterize(*params, view, K, 24, 20, background=bg)
    slow = rasterize_dense(*params, view, K, 24, 20, background=bg)
    assert fast["alpha"].max() > 0.9  # the case exercises saturation and the 1e-4 stop
    for k in ("rgb", "depth", "alpha"):
        scale = slow[k].abs().max().item()
        assert (fast[k] - slow[k]).abs().max().item() <= tol * max(scale, 1.0), k
    gf = torch.autograd.grad(_loss(fast), params)
    gs = torch.autograd.grad(_loss(slow), params)
    for name, a, b in zip(("means", "quats", "scales", "opacities", "sh"), gf, gs):
        assert torch.isfinite(a).all(), name
        err = (a - b).abs().max().item()
        assert err <= 5 * tol * max(b.abs().max().item(), 1.0), (name, err)


def test_early_stop_is_exercised_and_matches():
    # Many opaque Gaussians stacked: transmittance falls below 1e-4 inside the first block.
    params = _scene(300, torch.float64, seed=3)
    with torch.no_grad():
        params[3].fill_(0.95)
        params[2].mul_(3)
    view, K = _cam(dtype=torch.float64)
    fast = rasterize(*params, view, K, 24, 24)
    slow = rasterize_dense(*params, view, K, 24, 24)
    assert (1 - fast["alpha"]).min() < 1e-3
    assert torch.allclose(fast["rgb"], slow["rgb"], atol=1e-10)
    gf = torch.autograd.grad(_loss(fast), params)
    gs = torch.autograd.grad(_loss(slow), params)
    for a, b in zip(gf, gs):
        assert torch.allclose(a, b, atol=1e-8, rtol=1e-6)


@pytest.mark.parametrize("tile,block", [(4, 8), (8, 3), (16, 128)])
def test_tile_and_block_size_do_not_change_the_image(tile, block):
    params = _scene(150, torch.float64, seed=5)
    view, K = _cam(dtype=torch.float64)
    proj = project(*params[:3], view, K, 24, 24)
    feats = torch.rand(150, 4, dtype=torch.float64)
    bg = torch.rand(4, dtype=torch.float64)
    outs = []
    for t, b in ((8, 128), (tile, block)):
        ids, starts, tx, _ = raster.bin_tiles(proj["means2d"], proj["radii"], proj["depths"], proj["valid"], 24, 24, t)
        outs.append(raster.composite(proj["means2d"], proj["conics"], params[3], feats, bg, ids, starts, tx, 24, 24, t, b))
    assert torch.allclose(outs[0][0], outs[1][0], atol=1e-12)
    assert torch.allclose(outs[0][1], outs[1][1], atol=1e-12)


def test_gradcheck_composite_float64():
    g = torch.Generator().manual_seed(7)
    n, w, h = 6, 8, 8
    means2d = (torch.rand(n, 2, generator=g, dtype=torch.float64) * 6 + 1).requires_grad_()
    L = torch.rand(n, 2, 2, generator=g, dtype=torch.float64) + torch.eye(2, dtype=torch.float64)
    cov = L @ L.transpose(1, 2) * 2
    inv = torch.linalg.inv(cov)
    conics = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1).requires_grad_()
    opac = (torch.rand(n, generator=g, dtype=torch.float64) * 0.5 + 0.3).requires_grad_()
    colors = torch.rand(n, 4, generator=g, dtype=torch.float64).requires_grad_()
    bg = torch.rand(4, generator=g, dtype=torch.float64).requires_grad_()
    depths = torch.arange(n, dtype=torch.float64)
    radii = torch.full((n,), 50.0, dtype=torch.float64)  # every Gaussian in every tile
    ids, starts, tx, _ = raster.bin_tiles(means2d, radii, depths, torch.ones(n, dtype=torch.bool), w, h, 4)

    # Huge support so no pixel sits on the 3-sigma cut (a discontinuity gradcheck would trip on).
    old = raster.SUPPORT_SIGMA
    raster.SUPPORT_SIGMA = 1e3
    try:
        def f(m, c, o, col, b):
            out, alpha = raster.composite(m, c, o, col, b, ids, starts, tx, w, h, 4, 2)
            return out, alpha
        assert torch.autograd.gradcheck(f, (means2d, conics, opac, colors, bg), eps=1e-6, atol=1e-6)
    finally:
        raster.SUPPORT_SIGMA = old


def test_projection_matches_pinhole_and_first_order_covariance():
    cam = Camera.from_ypr([1.0, -2.0, 3.0], 30.0, -20.0, 5.0, fov_deg=70, width=40, height=30)
    view = torch.tensor(cam.w2c)
    K = torch.tensor(cam.K)
    rng = np.random.default_rng(0)
    pts = cam.center + cam.forward * 8 + rng.normal(size=(20, 3))
    quats = torch.tensor(rng.normal(size=(20, 4)))
    scales = torch.tensor(rng.uniform(0.05, 0.3, size=(20, 3)))
    out = project(torch.tensor(pts), quats, scales, view, K, 40, 30)
    uv, z = cam.project(pts)
    assert np.allclose(out["means2d"].numpy(), uv, atol=1e-9)
    assert np.allclose(out["depths"].numpy(), z, atol=1e-9)

    # Covariance: J Sigma J^T with J the autograd Jacobian of the camera projection (all these
    # centres are well inside the view, so the 3DGS Jacobian clamp is inactive).
    def proj_fn(p):
        c = view[:3, :3] @ p + view[:3, 3]
        return torch.stack([K[0, 0] * c[0] / c[2] + K[0, 2], K[1, 1] * c[1] / c[2] + K[1, 2]])

    from scipy.spatial.transform import Rotation

    for i in range(20):
        J = torch.autograd.functional.jacobian(proj_fn, torch.tensor(pts[i])).numpy()
        q = quats[i].numpy()
        R = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()  # scipy wants xyzw
        S = np.diag(scales[i].numpy())
        cov = J @ R @ S @ S @ R.T @ J.T + BLUR_PX2 * np.eye(2)
        a, b, c = out["conics"][i].numpy()
        assert np.allclose(np.linalg.inv([[a, b], [b, c]]), cov, rtol=1e-9), i


def _fibonacci_sphere(n):
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5 ** 0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], -1)


def test_sh_basis_is_orthonormal_real_sh():
    # Closed form: the 16 real SH basis functions are orthonormal on the unit sphere.
    dirs = torch.tensor(_fibonacci_sphere(40000))
    basis = []
    for k in range(16):
        sh = torch.zeros(len(dirs), 16, 3, dtype=torch.float64)
        sh[:, k, 0] = 0.1  # small so value + 0.5 stays above the clamp at 0
        basis.append((eval_sh(3, sh, dirs)[:, 0] - 0.5) / 0.1)
    B = torch.stack(basis, 1).numpy()
    gram = B.T @ B * (4 * np.pi / len(dirs))
    assert np.allclose(gram, np.eye(16), atol=2e-3)
    # And degree 1 is linear in the direction (Y_1 ~ y, z, x with 3DGS's signs).
    assert np.allclose(B[:, 1], -math.sqrt(3 / (4 * np.pi)) * dirs[:, 1].numpy(), atol=1e-9)


def _finite_everything(params, view, K, w, h):
    out = rasterize(*params, view, K, w, h, background=torch.tensor([0.2, 0.3, 0.4]))
    for k in ("rgb", "depth", "alpha"):
        assert torch.isfinite(out[k]).all(), k
    grads = torch.autograd.grad(_loss(out), params, allow_unused=True)
    for name, g in zip(("means", "quats", "scales", "opacities", "sh"), grads):
        assert g is None or torch.isfinite(g).all(), name
    return out


@pytest.mark.parametrize("case", ["tiny_scales", "huge_scales", "behind", "near_plane", "needle",
                                  "opacity_0_1", "zero_quat"])
def test_stiff_cases_stay_finite(case):
    params = _scene(60, seed=11)
    view, K = _cam(32)
    with torch.no_grad():
        means, quats, scales, opac, sh = params
        if case == "tiny_scales":
            scales.fill_(1e-9)
        elif case == "huge_scales":
            scales[:10] = 1e5
        elif case == "behind":
            means[:30, 2] = -means[:30, 2]
            means[30:40, 2] = 0.0
        elif case == "near_plane":
            means[:, 2] = torch.linspace(-0.5, 0.5, 60)
            scales.fill_(1.0)
        elif case == "needle":
            scales[:, 0] = 50.0
            scales[:, 1:] = 1e-7
        elif case == "opacity_0_1":
            opac[:30] = 0.0
            opac[30:] = 1.0
        elif case == "zero_quat":
            quats[:5] = 0.0
    out = _finite_everything(params, view, K, 32, 32)
    if case == "opacity_0_1":
        assert out["alpha"].max() <= 1.0


def test_grazing_ground_view_pitch0_from_2m():
    # A ground camera 2 m above a plane of flat Gaussians, looking at the horizon.
    cam = Camera.from_ypr([0.0, 0.0, 2.0], 0.0, 0.0, fov_deg=90, width=32, height=32)
    xs, ys = torch.meshgrid(torch.linspace(-40, 40, 40), torch.linspace(-40, 40, 40), indexing="ij")
    n = xs.numel()
    means = torch.stack([xs.reshape(-1), ys.reshape(-1), torch.zeros(n)], -1).requires_grad_()
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1).requires_grad_()
    scales = torch.tensor([[1.2, 1.2, 1e-6]]).repeat(n, 1).requires_grad_()
    opac = torch.full((n,), 0.9).requires_grad_()
    sh = torch.rand(n, 1, 3).requires_grad_()
    out = _finite_everything([means, quats, scales, opac, sh], torch.tensor(cam.w2c, dtype=torch.float32),
                             torch.tensor(cam.K, dtype=torch.float32), 32, 32)
    # Below the horizon (row 16) the ground is opaque. Above it only the first-order (EWA)
    # footprints of the discs next to the camera leak, which is the approximation, not a bug.
    assert out["alpha"][20:].mean() > 0.9 and out["alpha"][0].mean() < 0.5 * out["alpha"][-1].mean()


def test_gsplat_path_when_cuda():
    pytest.importorskip("gsplat")
    if not torch.cuda.is_available():
        pytest.skip("gsplat dispatch needs CUDA")
    params = [p.detach().cuda() for p in _scene(100)]
    view, K = _cam()
    a = rasterize(*params, view.cuda(), K.cuda(), 24, 24)
    b = rasterize(*[p.cpu() for p in params], view, K, 24, 24)
    assert torch.allclose(a["rgb"].cpu(), b["rgb"], atol=2e-2)


def test_sh_degree_beyond_the_coefficients_is_refused():
    params = _scene(5, sh_bases=1)
    view, K = _cam()
    for fn in (rasterize, rasterize_dense):
        with pytest.raises(AssertionError, match="sh_degree 1 needs 4 SH bases, sh has 1"):
            fn(*params, view, K, 24, 24, sh_degree=1)
    assert rasterize(*params, view, K, 24, 24, sh_degree=0)["rgb"].shape == (24, 24, 3)


# --------------------------------------------------------------------------- units the image tests pass through

P = importlib.import_module("reference.common.gaussians.project")  # the package exports `project` the function

def test_sh_basis_counts():
    assert [P.num_sh_bases(d) for d in range(4)] == [1, 4, 9, 16]
    assert [P.degree_for(n) for n in (1, 4, 9, 16)] == [0, 1, 2, 3]


def test_quat_to_rotmat_matches_scipy_for_any_norm():
    from scipy.spatial.transform import Rotation

    g = torch.Generator().manual_seed(3)
    q = torch.randn(10, 4, generator=g, dtype=torch.float64) * 3.0  # wxyz, not normalised
    got = P.quat_to_rotmat(q)
    assert got.shape == (10, 3, 3)
    want = Rotation.from_quat(q[:, [1, 2, 3, 0]].numpy()).as_matrix()  # scipy: scalar last, normalises
    np.testing.assert_allclose(got.numpy(), want, atol=1e-12)


def test_outputs_keep_the_dtype_of_the_means():
    """Cameras usually come in float64, Gaussians in float32: the projection works in float64
    and hands back the Gaussians' dtype (the rasterizer's buffers follow it)."""
    means, quats, scales, _, _ = (t.detach() for t in _scene(30))
    view, K = _cam(dtype=torch.float64)
    out = P.project(means, quats, scales, view, K, 24, 20)
    assert {k: v.dtype for k, v in out.items() if k != "valid"} == dict.fromkeys(
        ("means2d", "conics", "depths", "radii"), torch.float32)
    assert P.view_dirs(means, view).dtype == torch.float32
    out64 = P.project(means.double(), quats, scales, view, K, 24, 20)
    assert out64["conics"].dtype == torch.float64
    torch.testing.assert_close(out64["conics"].float(), out["conics"])


@pytest.mark.parametrize("at", [(4.0, 4.0), (20.0, 12.0)])  # centres of the first tile and the last column's
def test_a_gaussian_that_touches_one_tile(at):
    """One small Gaussian inside one 8x8 tile: the only non-empty tile is still composited."""
    view, K = _cam(dtype=torch.float64)
    x, y = at
    z = 5.0
    means = torch.tensor([[(x - K[0, 2].item()) * z / K[0, 0].item(), (y - K[1, 2].item()) * z / K[1, 1].item(), z]],
                         dtype=torch.float64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    scales = torch.full((1, 3), 0.02, dtype=torch.float64)  # 0.06 px; with the blur, radius 1.7 px
    opac = torch.tensor([0.9], dtype=torch.float64)
    sh = torch.ones(1, 1, 3, dtype=torch.float64)
    proj = P.project(means, quats, scales, view, K, 24, 20)
    assert 1.0 < proj["radii"].item() < 2.0
    starts = raster.bin_tiles(*(proj[k] for k in ("means2d", "radii", "depths", "valid")), 24, 20, tile=8)[1]
    assert int(((starts[1:] - starts[:-1]) > 0).sum()) == 1
    fast = rasterize(means, quats, scales, opac, sh, view, K, 24, 20, tile=8)
    slow = rasterize_dense(means, quats, scales, opac, sh, view, K, 24, 20)
    assert slow["alpha"].max() > 0.05
    for k in ("rgb", "depth", "alpha"):
        torch.testing.assert_close(fast[k], slow[k], rtol=1e-9, atol=1e-9)
