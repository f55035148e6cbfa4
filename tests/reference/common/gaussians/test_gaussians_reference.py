"""The splatting path (project, sh_colors, rasterize) against tests/builders/gaussians_reference.py,
a per-Gaussian, per-pixel numpy transcription of the 3DGS forward pass that shares no code with
it (own quaternion, covariance, Jacobian clamp, SH constants from closed forms, compositing).
The dense rasterizer in reference/ shares `project` and `sh_colors` with the fast path, so only
this comparison can catch a projection or SH bug."""

import math

import numpy as np
import pytest
import torch
from builders import gaussians_reference as ref

from reference.common.gaussians import project, rasterize
from reference.common.gaussians.project import sh_colors
from skyeyes_bench.cameras import Camera

W, H = 20, 16


def _camera():
    cam = Camera.from_ypr([0.5, -1.0, 2.0], 25.0, -10.0, 3.0, fov_deg=70, width=W, height=H)
    return cam, np.asarray(cam.w2c, np.float64), np.asarray(cam.K, np.float64)


def _scene(cam, n_inside=40, n_edge=30, seed=0, sh_bases=16):
    """Gaussians in view, plus large ones whose centres lie 1.4-2.4 x tan(fov/2) off-axis (outside
    the image, where the 3DGS Jacobian clamp at 1.3 is active) but reach into it."""
    rng = np.random.default_rng(seed)
    R = np.asarray(cam.c2w)[:3, :3]
    tan_x, tan_y = W / (2 * cam.K[0, 0]), H / (2 * cam.K[1, 1])
    z = rng.uniform(3.0, 8.0, n_inside + n_edge)
    off = rng.choice([-1, 1], n_edge) * rng.uniform(1.4, 2.4, n_edge)  # beyond the clamp
    across = rng.uniform(-1.2, 1.2, n_edge)
    side = np.arange(n_edge) % 2 == 0  # half off the left/right edges, half off the top/bottom
    xn = np.concatenate([rng.uniform(-0.9, 0.9, n_inside), np.where(side, off, across)]) * tan_x
    yn = np.concatenate([rng.uniform(-0.9, 0.9, n_inside), np.where(side, across, off)]) * tan_y
    local = np.stack([xn * z, yn * z, z], -1)
    means = local @ R.T + np.asarray(cam.center)
    scales = np.concatenate([rng.uniform(0.03, 0.3, (n_inside, 3)), rng.uniform(0.8, 2.5, (n_edge, 3))])
    quats = rng.normal(size=(len(z), 4))
    opac = rng.uniform(0.1, 0.95, len(z))
    sh = rng.normal(0, 0.3, (len(z), sh_bases, 3))
    return means, quats, scales, opac, sh


def _t(*arrays):
    return [torch.tensor(a, dtype=torch.float64) for a in arrays]


def test_project_matches_the_3dgs_transcription():
    cam, view, K = _camera()
    means, quats, scales, _, _ = _scene(cam)
    out = project(*_t(means, quats, scales, view, K), W, H)
    pre = ref.preprocess(means, quats, scales, view, K, W, H)
    clamped = [0, 0]
    for i, p in enumerate(pre):
        on = p is not None and (p["uv"][0] + p["radius"] > 0 and p["uv"][0] - p["radius"] < W
                                and p["uv"][1] + p["radius"] > 0 and p["uv"][1] - p["radius"] < H)
        assert bool(out["valid"][i]) == on, i
        if not on:
            continue
        np.testing.assert_allclose(out["means2d"][i].numpy(), p["uv"], rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(out["conics"][i].numpy(), p["conic"], rtol=1e-9, atol=1e-12)
        assert out["depths"][i].item() == pytest.approx(p["depth"], rel=1e-12)
        assert out["radii"][i].item() == pytest.approx(p["radius"], rel=1e-9)
        t = view[:3, :3] @ means[i] + view[:3, 3]
        clamped[0] += abs(t[0] / t[2]) > ref.JACOBIAN_LIMIT * W / (2 * K[0, 0])
        clamped[1] += abs(t[1] / t[2]) > ref.JACOBIAN_LIMIT * H / (2 * K[1, 1])
    assert min(clamped) >= 4, clamped  # the clamp is exercised in x and in y on Gaussians that are drawn


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_colours_match_the_3dgs_transcription(degree):
    cam, view, K = _camera()
    means, _, _, _, sh = _scene(cam, seed=degree)
    got = sh_colors(*_t(sh, means, view), degree).numpy()
    campos = np.asarray(cam.center, np.float64)
    want = np.stack([ref.color_from_sh(degree, sh[i], means[i], campos) for i in range(len(means))])
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_rasterize_matches_the_3dgs_transcription_pixel_by_pixel():
    cam, view, K = _camera()
    means, quats, scales, opac, sh = _scene(cam, seed=3)
    bg = np.array([0.1, 0.2, 0.3])
    fast = rasterize(*_t(means, quats, scales, opac, sh, view, K), W, H, background=torch.tensor(bg))
    slow = ref.render(means, quats, scales, opac, sh, view, K, W, H, background=bg)
    assert slow["alpha"].max() > 0.9 and slow["alpha"].min() < 0.5
    for k in ("rgb", "depth", "alpha"):
        np.testing.assert_allclose(fast[k].detach().numpy(), slow[k], rtol=0, atol=1e-9, err_msg=k)
    # The comparison can see the clamp: the same transcription with the limit doubled differs.
    old = ref.JACOBIAN_LIMIT
    try:
        ref.JACOBIAN_LIMIT = 2 * old
        other = ref.render(means, quats, scales, opac, sh, view, K, W, H, background=bg)
    finally:
        ref.JACOBIAN_LIMIT = old
    assert np.abs(other["rgb"] - slow["rgb"]).max() > 1e-3
    assert math.isfinite(float(fast["rgb"].sum()))
