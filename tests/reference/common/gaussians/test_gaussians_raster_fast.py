"""The fast paths of the tile rasterizer (issue 6) against slow references: exact tile binning vs
a per-pixel brute force and vs square binning, the clamped-alpha and stopping paths vs the dense
compositor, the no-grad forward, and the SH / depth-sort shortcuts."""

import pytest
import torch

from reference.common.gaussians import project, rasterize, rasterize_dense
from reference.common.gaussians import raster
from reference.common.gaussians.project import eval_sh, sh_basis

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _scene(n, dtype=torch.float64, seed=0, opac_lo=0.0, opac_hi=1.0):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([1.2, 1.0, 0.5], dtype=dtype)
    means[:, 2] += 5.0
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    # Anisotropic: needles and discs, so ellipses cut tiles at every angle.
    scales = torch.rand(n, 3, generator=g, dtype=dtype) ** 2 * 0.3 + 0.01
    opac = opac_lo + (opac_hi - opac_lo) * torch.rand(n, generator=g, dtype=dtype)
    sh = torch.randn(n, 4, 3, generator=g, dtype=dtype) * 0.3
    return [t.requires_grad_() for t in (means, quats, scales, opac, sh)]


def _cam(w, h, dtype=torch.float64):
    K = torch.tensor([[w * 0.8, 0, w / 2], [0, w * 0.8, h / 2], [0, 0, 1.0]], dtype=dtype)
    return torch.eye(4, dtype=dtype), K


def _pairs(ids, starts):
    out = set()
    for t in range(len(starts) - 1):
        out.update((t, g) for g in ids[starts[t]:starts[t + 1]].tolist())
    return out


@pytest.mark.parametrize("tile", [2, 4, 8])
def test_exact_binning_keeps_every_contributing_pair(tile):
    # Brute force: every (pixel, Gaussian) with q <= 9 and o exp(-q/2) >= 1/255 must be listed
    # for the pixel's tile; the image (30 x 22) is not a multiple of the tile size.
    w, h = 30, 22
    params = _scene(300, seed=1)
    with torch.no_grad():
        params[3][:20] = 0.5 / 255  # can never reach 1/255: must be dropped entirely
        params[3][20:40] = 1.0
    view, K = _cam(w, h)
    proj = project(*params[:3], view, K, w, h)
    o = params[3].detach()
    ids, starts, tx, _ = raster.bin_tiles(proj["means2d"], proj["radii"], proj["depths"], proj["valid"], w, h, tile,
                                         conics=proj["conics"], opacities=o)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64) + 0.5, torch.arange(w, dtype=torch.float64) + 0.5,
                            indexing="ij")
    m, c = proj["means2d"].detach(), proj["conics"].detach()
    dx, dy = xs.reshape(1, -1) - m[:, :1], ys.reshape(1, -1) - m[:, 1:]
    q = c[:, :1] * dx * dx + 2 * c[:, 1:2] * dx * dy + c[:, 2:] * dy * dy
    hit = (q <= 9) & (o[:, None] * torch.exp(-q / 2) >= 1 / 255) & proj["valid"][:, None]
    tile_of = ((ys.reshape(-1) // tile) * tx + xs.reshape(-1) // tile).long()
    need = {(int(tile_of[p]), gi) for gi, p in hit.nonzero().tolist()}
    have = _pairs(ids, starts)
    assert need and need <= have
    assert not any(gi < 20 for _, gi in have)
    # Tight: few listed pairs reach no pixel (the square binning lists several times more).
    assert len(have) <= 1.3 * len(need)
    # Each tile's list is in depth order.
    d = proj["depths"].detach()
    for t in range(len(starts) - 1):
        seg = d[ids[starts[t]:starts[t + 1]]]
        assert torch.all(seg[1:] >= seg[:-1])


def test_exact_binning_gives_the_same_image_and_gradients_as_square_binning():
    w, h = 26, 19
    params = _scene(200, seed=2)
    view, K = _cam(w, h)
    proj = project(*params[:3], view, K, w, h)
    feats = torch.rand(200, 4, dtype=torch.float64, requires_grad=True)
    bg = torch.rand(4, dtype=torch.float64)
    ins = (proj["means2d"], proj["conics"], params[3], feats)
    outs = []
    for exact in (False, True):
        kw = {"conics": proj["conics"], "opacities": params[3]} if exact else {}
        ids, starts, tx, _ = raster.bin_tiles(proj["means2d"], proj["radii"], proj["depths"], proj["valid"], w, h, 4,
                                             **kw)
        out, alpha = raster.composite(*ins, bg, ids, starts, tx, w, h, 4, 16)
        loss = (out * torch.linspace(-1, 1, out.numel(), dtype=torch.float64).reshape(out.shape)).sum() + alpha.sum()
        outs.append((out, alpha, torch.autograd.grad(loss, params + [feats], allow_unused=True, retain_graph=True)))
    (o0, a0, g0), (o1, a1, g1) = outs
    assert torch.allclose(o0, o1, atol=1e-12) and torch.allclose(a0, a1, atol=1e-12)
    for x, y in zip(g0, g1):
        assert (x is None) == (y is None)
        if x is not None:
            assert torch.allclose(x, y, atol=1e-10)


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-9), (torch.float32, 2e-4)])
def test_clamped_alphas_and_stops_match_dense(dtype, tol):
    # Opacities up to 1: alpha clamps at 0.99 (its own gradient path) and pixels stop early.
    params = _scene(150, dtype, seed=4, opac_lo=0.6, opac_hi=1.0)
    with torch.no_grad():
        params[3][::3] = 1.0
        params[2].mul_(1.5)
    view, K = _cam(24, 20, dtype)
    bg = torch.tensor([0.3, 0.1, 0.2], dtype=dtype)
    fast = rasterize(*params, view, K, 24, 20, background=bg)
    slow = rasterize_dense(*params, view, K, 24, 20, background=bg)
    assert (1 - fast["alpha"]).min() < 1e-3
    for k in ("rgb", "depth", "alpha"):
        assert (fast[k] - slow[k]).abs().max().item() <= tol * max(slow[k].abs().max().item(), 1.0), k
    g = torch.Generator().manual_seed(9)
    wr = torch.randn(20, 24, 3, generator=g, dtype=dtype)

    def loss(o):
        return (o["rgb"] * wr).sum() + 0.1 * o["depth"].sum() + o["alpha"].sum()

    gf = torch.autograd.grad(loss(fast), params)
    gs = torch.autograd.grad(loss(slow), params)
    for name, a, b in zip(("means", "quats", "scales", "opacities", "sh"), gf, gs):
        assert torch.isfinite(a).all(), name
        assert (a - b).abs().max().item() <= 5 * tol * max(b.abs().max().item(), 1.0), name


def test_no_grad_forward_equals_grad_forward():
    params = _scene(120, torch.float32, seed=6)
    view, K = _cam(20, 20, torch.float32)
    with torch.no_grad():
        a = rasterize(*params, view, K, 20, 20)
    b = rasterize(*params, view, K, 20, 20)
    for k in ("rgb", "depth", "alpha"):
        assert torch.equal(a[k], b[k].detach()), k


def test_sh_dot_matches_termwise_sum_and_its_gradient():
    g = torch.Generator().manual_seed(3)
    dirs = torch.nn.functional.normalize(torch.randn(50, 3, generator=g, dtype=torch.float64), dim=-1)
    dirs.requires_grad_()
    sh = torch.randn(50, 16, 3, generator=g, dtype=torch.float64, requires_grad=True)
    fast = eval_sh(3, sh, dirs)
    ref = ((sh_basis(3, dirs)[:, :, None] * sh).sum(1) + 0.5).clamp_min(0.0)
    assert torch.allclose(fast, ref, atol=1e-14)
    w = torch.randn(50, 3, generator=g, dtype=torch.float64)
    for a, b in zip(torch.autograd.grad((fast * w).sum(), (sh, dirs)), torch.autograd.grad((ref * w).sum(), (sh, dirs))):
        assert torch.allclose(a, b, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_depth_argsort_is_the_stable_float_argsort(dtype):
    d = torch.tensor([3.0, 1.0, 2.0, 1.0, 1e-3, 7e5, 2.0], dtype=dtype).repeat(50)
    assert torch.equal(raster._argsort_depths(d), torch.argsort(d, stable=True))
    d[5] = -1.0  # not all positive: falls back to the float sort
    assert torch.equal(raster._argsort_depths(d), torch.argsort(d, stable=True))
