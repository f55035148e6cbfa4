"""The compact Instant-NGP's cores against slow references and closed forms: the hash encoding
(a per-point, per-level Python loop), the volume-rendering weights (a homogeneous slab), the
far field's contraction and the ray sampling."""

import math

import numpy as np
import pytest
import torch

from reference.common.nerf import (HashEncoding, HashGridConfig, OccupancyGrid, level_resolutions,
                                   render_weights)
from reference.common.nerf.render import SceneBox, composite, contract, distortion_loss, sample_intervals

pytestmark = pytest.mark.usefixtures("one_torch_thread")

P1, P2, P3 = 1, 2654435761, 805459861  # the paper's primes, written out again


def reference_encode(table: torch.Tensor, x: torch.Tensor, resolutions: list[int]) -> torch.Tensor:
    """Slow: loops over points, levels and the 8 corners in Python integers (autograd through
    the trilinear weights and the table reads)."""
    L, T, F = table.shape
    rows = []
    for p in range(len(x)):
        feats = []
        for lvl, n in enumerate(resolutions):
            dense = (n + 1) ** 3 <= T
            pos = [x[p, k] * n for k in range(3)]
            cell = [min(max(math.floor(float(pos[k].detach())), 0), n - 1) for k in range(3)]
            frac = [pos[k] - cell[k] for k in range(3)]
            acc = torch.zeros(F, dtype=table.dtype)
            for a in (0, 1):
                for b in (0, 1):
                    for c in (0, 1):
                        i, j, k = cell[0] + a, cell[1] + b, cell[2] + c
                        idx = i + j * (n + 1) + k * (n + 1) ** 2 if dense else ((i * P1) ^ (j * P2) ^ (k * P3)) % T
                        w = (frac[0] if a else 1 - frac[0]) * (frac[1] if b else 1 - frac[1]) * (
                            frac[2] if c else 1 - frac[2])
                        acc = acc + w * table[lvl, idx]
            feats.append(acc)
        rows.append(torch.cat(feats))
    return torch.stack(rows)


def test_level_resolutions_follow_the_geometric_growth():
    assert level_resolutions(HashGridConfig(levels=4, n_min=2, n_max=16)) == [2, 4, 8, 16]
    # b = (512 / 16)^(1/7): N_l = floor(16 * 32^(l / 7)), e.g. 16 * 32^(5/7) = 190.2
    assert level_resolutions(HashGridConfig(levels=8, n_min=16, n_max=512)) == [16, 26, 43, 70, 115, 190, 312, 512]


def _points(resolutions, n_random=20, seed=0):
    g = torch.Generator().manual_seed(seed)
    pts = [torch.rand(n_random, 3, generator=g, dtype=torch.float64)]
    # on cell faces, edges and corners of every level, and the cube's corners
    for n in resolutions:
        pts.append(torch.tensor([[1 / n, 0.5, 0.3], [2 / n, 1 / n, 0.77], [1 / n, 1 / n, 1 / n]], dtype=torch.float64))
    pts.append(torch.tensor([[0, 0, 0], [1, 1, 1], [1, 0, 1], [0.5, 0.5, 0.5]], dtype=torch.float64))
    return torch.cat(pts)


@pytest.mark.parametrize("cfg", [
    HashGridConfig(levels=3, log2_T=6, features=2, n_min=2, n_max=8),  # level 0 dense, 1-2 hashed
    HashGridConfig(levels=2, log2_T=3, features=3, n_min=3, n_max=5),  # T = 8: collisions everywhere
])
def test_hash_encoding_matches_the_python_loop_forward_and_backward(cfg):
    enc = HashEncoding(cfg, generator=torch.Generator().manual_seed(1)).double()
    with torch.no_grad():
        enc.table.normal_(generator=torch.Generator().manual_seed(2))  # O(1) features, not 1e-4
    res = level_resolutions(cfg)
    x = _points(res)
    # Collisions do happen in the second config: more vertices than table rows on a level.
    if cfg.log2_T == 3:
        assert (res[0] + 1) ** 3 > 2 ** cfg.log2_T
    xa = x.clone().requires_grad_()
    ta = enc.table.detach().clone().requires_grad_()
    want = reference_encode(ta, xa, res)
    xb = x.clone().requires_grad_()
    got = enc(xb)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    g = torch.randn(want.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    want_dt, want_dx = torch.autograd.grad(want, (ta, xa), g)
    got_dt, got_dx = torch.autograd.grad(got, (enc.table, xb), g)
    torch.testing.assert_close(got_dt, want_dt, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(got_dx, want_dx, rtol=1e-10, atol=1e-10)


def test_hash_encoding_is_continuous_across_a_cell_face():
    enc = HashEncoding(HashGridConfig(levels=1, log2_T=10, features=2, n_min=4, n_max=4)).double()
    with torch.no_grad():
        enc.table.normal_(generator=torch.Generator().manual_seed(0))
    x = torch.tensor([[0.25 - 1e-12, 0.4, 0.6], [0.25, 0.4, 0.6], [0.25 + 1e-12, 0.4, 0.6]], dtype=torch.float64)
    y = enc(x)
    torch.testing.assert_close(y[0], y[1], atol=1e-9, rtol=0)
    torch.testing.assert_close(y[2], y[1], atol=1e-9, rtol=0)


def test_gradcheck_encoding_and_rendering_in_float64():
    enc = HashEncoding(HashGridConfig(levels=2, log2_T=5, features=2, n_min=2, n_max=4)).double()
    with torch.no_grad():
        enc.table.normal_(generator=torch.Generator().manual_seed(0))
    # points away from cell faces (finite differences must not cross one)
    x = (torch.tensor([[0.1, 0.3, 0.6], [0.7, 0.55, 0.15], [0.35, 0.8, 0.9]], dtype=torch.float64)
         ).requires_grad_()
    table = enc.table.detach().clone().requires_grad_()
    deltas = torch.tensor([[0.3, 0.5, 0.2]], dtype=torch.float64, requires_grad=True)

    def fn(t, x, deltas):
        h = HashEncoding.forward(_with_table(enc, t), x).sum(1)  # [3]: one ray of 3 samples
        w, left = render_weights(torch.nn.functional.softplus(h)[None], deltas)
        return torch.cat([w.reshape(-1), left])

    assert torch.autograd.gradcheck(fn, (table, x, deltas), eps=1e-6, atol=1e-7)


def _with_table(enc, t):
    """enc reading the checked tensor t as its table."""
    enc._parameters["table"] = t
    return enc


@pytest.mark.parametrize("sigma, length, n", [(2.0, 3.0, 7), (1e4, 1e-3, 5), (1e-6, 1e3, 4), (0.0, 5.0, 3),
                                              (50.0, 100.0, 10)])
def test_weights_of_a_homogeneous_slab_match_the_closed_form(sigma, length, n):
    sig = torch.full((2, n), sigma, dtype=torch.float32, requires_grad=True)
    dl = torch.full((2, n), length / n, dtype=torch.float32, requires_grad=True)
    w, left = render_weights(sig, dl)
    # closed form: T(s) = exp(-sigma s); sample i holds exp(-sigma i d) (1 - exp(-sigma d))
    d = length / n
    want_w = np.array([math.exp(-sigma * i * d) * -math.expm1(-sigma * d) for i in range(n)])
    want_left = math.exp(-sigma * length)
    np.testing.assert_allclose(w[0].detach().numpy(), want_w, rtol=2e-5, atol=1e-30)
    np.testing.assert_allclose(float(left[0]), want_left, rtol=2e-5, atol=1e-30)
    np.testing.assert_allclose(float(w[0].sum()), -math.expm1(-sigma * length), rtol=2e-5, atol=1e-30)
    (w.sum() + left.sum()).backward()
    assert torch.isfinite(sig.grad).all() and torch.isfinite(dl.grad).all()


def test_empty_rays_render_the_background():
    sig = torch.zeros(3, 0, requires_grad=True)
    w, left = render_weights(sig, torch.zeros(3, 0))
    assert w.shape == (3, 0) and torch.equal(left, torch.ones(3))
    rgb, acc = composite(w, torch.zeros(3, 0, 3), torch.tensor([0.2, 0.4, 0.6]))
    torch.testing.assert_close(rgb, torch.tensor([[0.2, 0.4, 0.6]] * 3))
    assert torch.equal(acc, torch.zeros(3))
    (rgb.sum() + left.sum()).backward()  # no error, nothing to reach


def test_contraction_is_the_identity_inside_and_maps_infinity_to_the_cube_of_side_4():
    y = torch.tensor([[0.3, -0.9, 1.0], [2.0, 0.0, 0.0], [0.0, -4.0, 1.0], [1e9, 1e8, -1e9]])
    c = contract(y)
    torch.testing.assert_close(c[0], y[0])
    torch.testing.assert_close(c[1], torch.tensor([1.5, 0.0, 0.0]))  # 2 - 1/2
    torch.testing.assert_close(c[2], torch.tensor([0.0, -1.75, 0.4375]))  # (2 - 1/4) y / 4
    assert c[3].abs().max() <= 2 and c[3].abs().max() > 1.999


def test_samples_cover_the_box_then_the_far_field():
    box = SceneBox(np.array([-10.0, -10, -1]), np.array([10.0, 10, 9]))
    o = torch.tensor([[0.0, 0, 20], [0.0, 0, 2], [50.0, 50, 50]])  # above, inside, and missing the box
    d = torch.nn.functional.normalize(torch.tensor([[0.0, 0.6, -0.8], [1.0, 0, 0], [0.0, 0, 1]]), dim=-1)
    t = sample_intervals(o, d, box, n_inner=8, n_outer=4, near=0.5, far=1000.0)
    assert t.shape == (3, 13) and (t[:, 1:] >= t[:, :-1]).all()
    # ray 0 enters through the top z = 9 (t = 11 / 0.8) and leaves through the side y = 10 (t = 10 / 0.6)
    torch.testing.assert_close(t[0, [0, 8]], torch.tensor([11 / 0.8, 10 / 0.6]))
    assert float(t[1, 0]) == pytest.approx(0.5) and float(t[1, 8]) == pytest.approx(10.0)
    assert float(t[2, 0]) == float(t[2, 8]) == pytest.approx(0.5)  # a miss: empty inner part
    assert float(t[:, -1].min()) == pytest.approx(1000.0)


def test_distortion_loss_matches_the_double_sum_and_prefers_a_surface_to_fog():
    g = torch.Generator().manual_seed(0)
    w = torch.rand(5, 7, generator=g, dtype=torch.float64) / 7
    S = w.shape[1]
    s = (torch.arange(S, dtype=torch.float64) + 0.5) / S

    def double_sum(w):  # the definition, O(S^2)
        return (w[:, :, None] * w[:, None, :] * (s[:, None] - s[None, :]).abs()).sum((1, 2)) + (w ** 2).sum(1) / (3 * S)

    torch.testing.assert_close(distortion_loss(w), double_sum(w), rtol=1e-12, atol=1e-15)
    wa = w.clone().requires_grad_()
    wb = w.clone().requires_grad_()
    g_out = torch.rand(5, generator=g, dtype=torch.float64)
    (ga,) = torch.autograd.grad(distortion_loss(wa), wa, g_out)
    (gb,) = torch.autograd.grad(double_sum(wb), wb, g_out)
    torch.testing.assert_close(ga, gb, rtol=1e-12, atol=1e-15)
    # the same total weight: one sample (a surface) against spread evenly (fog)
    surface = torch.zeros(1, 16)
    surface[0, 5] = 0.9
    fog = torch.full((1, 16), 0.9 / 16)
    assert float(distortion_loss(surface)) < 0.1 * float(distortion_loss(fog))
    assert distortion_loss(torch.zeros(3, 0)).shape == (3,)


def test_the_mean_clamp_keeps_the_denser_half_of_a_field_thinner_than_alpha_everywhere():
    g = torch.Generator().manual_seed(0)
    grid = OccupancyGrid(8, step_m=2.0, alpha=0.1)
    assert int(grid.inner.sum()) == 4 ** 3  # the middle half of each axis is the box
    grid.sigma = 0.018 + 1e-3 * torch.rand(8 ** 3, generator=g)  # a fresh field's haze: opacity ~0.036 < 0.1
    grid.refresh()
    assert not grid.occupied[grid.inner].any()  # alpha alone: every box cell skipped, nothing left to train
    clamped = OccupancyGrid(8, step_m=2.0, alpha=0.1, mean_clamp=True)
    clamped.sigma = grid.sigma.clone()
    clamped.refresh()
    opacity = -torch.expm1(-clamped.sigma * 2.0)[clamped.inner]
    assert torch.equal(clamped.occupied[clamped.inner], opacity > opacity.mean())  # the denser ~half
    assert 0.3 < float(clamped.occupied[clamped.inner].float().mean()) < 0.7
    shell_opacity = -torch.expm1(-clamped.sigma * clamped.step_m)[~clamped.inner]
    assert torch.equal(clamped.occupied[~clamped.inner], shell_opacity > 0.1)  # the shell: plain alpha
    # a surface above alpha: the clamp changes nothing (min(alpha, mean) = alpha)
    clamped.sigma = torch.full((8 ** 3,), 1e-4)
    clamped.sigma[clamped.inner.nonzero()[:5, 0]] = 5.0
    clamped.refresh()
    assert int(clamped.occupied[clamped.inner].sum()) == 5
    # the state survives a checkpoint
    again = OccupancyGrid(8, step_m=2.0, alpha=0.1, mean_clamp=True)
    again.load(clamped.state_dict())
    assert torch.equal(again.occupied, clamped.occupied)
