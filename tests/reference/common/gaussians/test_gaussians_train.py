"""Training pieces: torch SSIM vs scikit-image, densification bookkeeping, a tiny fit that
must improve, SuGaR's regularisation terms against closed forms."""

import math

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from reference.common.gaussians import rasterize
from reference.common.gaussians.model import GaussianModel
from reference.common.gaussians.ssim import ssim
from reference.common.gaussians.sugar_reg import SugarRegularizer, SugarWeights, sdf_terms
from reference.common.gaussians.train import TrainConfig, View, psnr, train



pytestmark = pytest.mark.usefixtures("one_torch_thread")

@pytest.mark.parametrize("shape", [(40, 37, 3), (16, 64, 3)])
def test_ssim_matches_skimage(shape):
    rng = np.random.default_rng(0)
    a = rng.random(shape)
    b = np.clip(a + 0.1 * rng.normal(size=shape), 0, 1)
    ref = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                data_range=1.0, channel_axis=2)
    ta = torch.tensor(a, requires_grad=True)
    val = ssim(ta, torch.tensor(b))
    assert abs(val.item() - ref) < 1e-10
    val.backward()
    assert torch.isfinite(ta.grad).all() and ta.grad.abs().sum() > 0
    assert abs(ssim(torch.tensor(a), torch.tensor(a)).item() - 1.0) < 1e-12


def _cloud(n, seed=0):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(size=(n, 3)) * [1.0, 1.0, 0.3] + [0, 0, 5]
    rgb = rng.random((n, 3))
    return xyz, rgb


def test_densify_bookkeeping_keeps_adam_state_aligned():
    m = GaussianModel.from_points(*_cloud(50), sh_degree=1)
    opt = m.make_optimizer({k: 1e-3 for k in m.params})
    loss = sum((v ** 2).sum() for v in m.params.values())
    loss.backward()
    opt.step()
    before = opt.state[m.params["means"]]["exp_avg"].clone()
    gen = torch.Generator().manual_seed(0)
    new = m.split_values(torch.tensor([0, 3]), 2, gen)
    m.append(opt, new)
    assert len(m) == 54
    for k, v in m.params.items():
        st = opt.state[v]
        assert st["exp_avg"].shape == v.shape, k
    assert torch.equal(opt.state[m.params["means"]]["exp_avg"][:50], before)
    assert (opt.state[m.params["means"]]["exp_avg"][50:] == 0).all()
    # Split children: scales shrink by 1/(0.8 * 2) (3DGS), centred on the parent on average.
    assert torch.allclose(torch.exp(new["log_scales"][:2]), m.scales[[0, 3]] / 1.6, rtol=1e-5)
    keep = torch.ones(54, dtype=torch.bool)
    keep[[1, 2]] = False
    m.keep(opt, keep)
    assert len(m) == 52 and opt.state[m.params["sh0"]]["exp_avg"].shape[0] == 52
    loss = sum((v ** 2).sum() for v in m.params.values())
    opt.zero_grad()
    loss.backward()
    opt.step()  # Adam accepts the rebuilt parameters


def test_tiny_fit_improves_and_densifies():
    # Target: a random "true" Gaussian set; fit from a perturbed, smaller cloud.
    torch.manual_seed(0)
    xyz, rgb = _cloud(80, seed=1)
    truth = GaussianModel.from_points(xyz, rgb, 0, opacity=0.8)
    K = torch.tensor([[20.0, 0, 16], [0, 20.0, 16], [0, 0, 1]])
    views = []
    for yaw in np.linspace(-0.3, 0.3, 4):
        c, s = math.cos(yaw), math.sin(yaw)
        R = torch.tensor([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])
        centre = torch.tensor([0.0, 0.0, 5.0])
        view = torch.eye(4)
        view[:3, :3] = R
        view[:3, 3] = -R @ centre + torch.tensor([0, 0, 5.0])
        with torch.no_grad():
            img = rasterize(truth.means, truth.quats, truth.scales, truth.opacities, truth.sh, view, K, 32, 32)["rgb"]
        views.append(View(img.clamp(0, 1), view, K))
    init = GaussianModel.from_points(xyz[::2] + 0.05 * np.random.default_rng(2).normal(size=(40, 3)),
                                     np.full((40, 3), 0.5), 0)

    def score(m):
        with torch.no_grad():
            return np.mean([psnr(rasterize(m.means, m.quats, m.scales, m.opacities, m.sh, v.viewmat, v.K, 32, 32)["rgb"],
                                 v.image) for v in views])

    p0 = score(init)
    cfg = TrainConfig(iterations=60, densify_from=10, densify_until=50, densify_every=10, sh_degree=0,
                      densify_grad=1e-5, max_gaussians=400, opacity_reset_every=0)
    stats = train(init, views, cfg, extent=2.0, progress=False)
    p1 = score(init)
    assert p1 > p0 + 1.5, (p0, p1)
    assert stats["gaussians"] > 40  # densification added Gaussians
    assert all(torch.isfinite(v).all() for v in init.params.values())


def test_box_pruning_drops_gaussians_outside_region():
    xyz, rgb = _cloud(60, seed=3)
    xyz[:10, 0] += 100.0  # far outside
    m = GaussianModel.from_points(xyz, rgb, 0, opacity=0.5)
    K = torch.tensor([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]])
    img = torch.rand(16, 16, 3)
    cfg = TrainConfig(iterations=2, densify_from=1, densify_until=3, densify_every=1, sh_degree=0,
                      max_gaussians=60, opacity_reset_every=0)
    box = torch.tensor([[-10.0, -10, -10], [10, 10, 20]])
    train(m, [View(img, torch.eye(4), K)], cfg, extent=5.0, box=box, progress=False)
    assert (m.means.detach()[:, 0] < 10).all()


def test_sugar_entropy_is_binary_entropy():
    m = GaussianModel.from_points(*_cloud(20), sh_degree=0)
    with torch.no_grad():
        m.params["logit_opacities"].copy_(torch.logit(torch.linspace(0.05, 0.95, 20)))
    reg = SugarRegularizer(SugarWeights(entropy_from=0, sdf_from=10**9, lambda_entropy=1.0))
    o = np.linspace(0.05, 0.95, 20)
    expect = np.mean(-o * np.log(o) - (1 - o) * np.log(1 - o))
    assert abs(reg(m, 1).item() - expect) < 1e-6


def test_sugar_normal_term_aligned_for_flat_isolated_gaussians():
    rng = np.random.default_rng(0)
    n = 30
    xyz = rng.uniform(-100, 100, size=(n, 3))  # far apart: each point sees one Gaussian
    m = GaussianModel.from_points(xyz, rng.random((n, 3)), 0, opacity=0.99)
    knn = torch.arange(n)[:, None]
    with torch.no_grad():
        m.params["quats"].copy_(torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32))
        m.params["log_scales"].copy_(torch.log(torch.tensor([[1.0, 1.0, 1e-3]])).repeat(n, 1))
    gen = torch.Generator().manual_seed(0)
    sdf, normal = sdf_terms(m, knn, 500, gen)
    assert normal.item() < 1e-2  # density gradient is along the smallest axis
    with torch.no_grad():
        m.params["log_scales"].zero_()  # isotropic: the 'normal' is arbitrary
    sdf_iso, normal_iso = sdf_terms(m, knn, 500, gen)
    assert normal_iso.item() > 0.1
    # Both terms are differentiable and finite.
    (sdf + normal).backward()
    for v in m.params.values():
        assert v.grad is None or torch.isfinite(v.grad).all()
