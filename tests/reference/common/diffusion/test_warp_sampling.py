"""Warped sampling (`vcm_warp`, issue 36): the backward warp against scipy's bilinear lookup and a
closed-form shift, the model-space mask against a loop, the held DDIM steps against the closed
form of the forward process, the sequence sampler's wiring, and the prior's depth of a plane."""

from __future__ import annotations

import dataclasses
import types

import numpy as np
import pytest
import torch
from scipy import ndimage

from reference.common.diffusion import core, sample, vcm, warp
from reference.common.gaussians.model import GaussianModel
from skyeyes_bench.cameras import Camera, intrinsics

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest: tiny tensors, one thread


def _cam(x: float = 0.0, yaw: float = 0.0, size: int = 16, fov: float = 60.0) -> Camera:
    """OpenCV axes as the world's (x right, y down, z ahead), turned by `yaw` degrees about y and
    moved x metres right."""
    a = np.deg2rad(yaw)
    c2w = np.eye(4)
    c2w[:3, :3] = [[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]]
    c2w[0, 3] = x
    return Camera(intrinsics(fov, size, size), c2w, size, size)


def test_warp_of_a_plane_is_the_closed_form_shift():
    """A fronto-parallel plane at depth d, the camera moved b sideways: every pixel's source lies
    f b / d pixels over, and a linear ramp warps to the ramp shifted by exactly that."""
    d, b, size = 4.0, 0.25, 16
    src_cam, dst_cam = _cam(0.0), _cam(b)
    depth = np.full((size, size), d)
    uv, valid = warp.warp_coords(depth, dst_cam, depth, src_cam, warp.DEPTH_TOL)
    f = src_cam.K[0, 0]
    u = np.arange(size) + 0.5
    shift = f * b / d
    want_valid = np.broadcast_to((u + shift <= size - 0.5)[None, :], (size, size))
    np.testing.assert_array_equal(valid, want_valid)
    np.testing.assert_allclose(uv[valid][:, 0], np.broadcast_to(u + shift, (size, size))[valid], atol=1e-9)
    ramp = torch.as_tensor(np.broadcast_to(0.03 * u, (size, size)).copy(), dtype=torch.float64)[None]
    out = warp.warp_image(ramp, uv, valid)[0].numpy()
    np.testing.assert_allclose(out[valid], (0.03 * (u + shift))[None, :].repeat(size, 0)[valid], atol=1e-9)
    assert (out[~valid] == 0).all()


def test_warp_image_is_scipys_bilinear_lookup():
    rng = np.random.default_rng(0)
    img = torch.as_tensor(rng.random((3, 12, 12)))
    cam0, cam1 = _cam(0.0, size=12), _cam(0.1, yaw=4.0, size=12)
    depth0 = 3.0 + rng.random((12, 12))
    depth1 = np.full((12, 12), 3.4)
    uv, valid = warp.warp_coords(depth1, cam1, depth0, cam0, 1.0)  # wide tolerance: many valid pixels
    assert 20 < valid.sum() < valid.size
    got = warp.warp_image(img, uv, valid).numpy()
    for c in range(3):  # scipy indexes pixel centres at integers: (v - 0.5, u - 0.5)
        want = ndimage.map_coordinates(img[c].numpy(), [uv[valid][:, 1] - 0.5, uv[valid][:, 0] - 0.5], order=1)
        np.testing.assert_allclose(got[c][valid], want, atol=1e-12)


def test_mask_in_model_space_needs_the_whole_patch():
    cfg = core.CoreConfig(resolution=8, patch=2)
    valid = torch.ones(1, 1, 8, 8, dtype=torch.bool)
    valid[0, 0, 3, 4] = False  # patch (1, 2)
    valid[0, 0, 7, 0] = False  # patch (3, 0)
    m = warp.encode_mask(valid, cfg, 12)
    assert m.shape == (1, 12, 4, 4)
    want = np.ones((4, 4))
    for i in range(4):
        for j in range(4):
            want[i, j] = float(valid[0, 0, 2 * i:2 * i + 2, 2 * j:2 * j + 2].all())
    for c in range(12):
        np.testing.assert_array_equal(m[0, c].numpy(), want)
    assert want.sum() == 14


class Shrink(torch.nn.Module):
    """eps = x_t / 2, each row alone; records its inputs (a noise-dependent, per-frame model)."""

    def __init__(self, cfg):
        super().__init__()
        self.cfg, self.calls = cfg, []
        self.w = torch.nn.Parameter(torch.zeros(1))
        self._vcm_context = vcm.ClipContext()  # what `clip_frames` sets (a VCM's)

    def forward(self, x_t, t, cond=None):
        self.calls.append((x_t.clone(), t.clone()))
        return x_t / 2


def _alpha_bar(cfg) -> np.ndarray:
    betas = np.linspace(cfg.beta_start, cfg.beta_end, cfg.train_timesteps, dtype=np.float64)
    return np.cumprod(1.0 - betas)


CFG = core.CoreConfig(resolution=8, prediction="epsilon")


def test_held_steps_are_the_forward_process_of_the_target():
    """After each of the first `hold` steps the masked pixels are sqrt(ab_t) target + sqrt(1 -
    ab_t) noise at the next timestep (closed form), the others the model's own; after them the
    model runs free. hold = steps ends on the target; a zero mask changes nothing."""
    steps, f = 5, 3
    g = torch.Generator().manual_seed(0)
    first = torch.randn(3, 8, 8, generator=g)
    noise = torch.randn(f - 1, 3, 8, 8, generator=g)
    target = torch.randn(f - 1, 3, 8, 8, generator=g)
    mask = torch.zeros(f - 1, 3, 8, 8)
    mask[..., :4] = 1.0
    conds = torch.zeros(f, 3, 8, 8)
    free_model = Shrink(CFG)
    free = sample.ddim_clip(free_model, conds, first, steps=steps, noise=noise)
    for hold in (1, 3):
        m = Shrink(CFG)
        out = sample.ddim_clip(m, conds, first, steps=steps, noise=noise, held=(target, mask), hold=hold)
        ab = _alpha_bar(CFG)
        for k in range(1, hold + 1):  # the model's input at step k: held through step k - 1
            x_t, t = m.calls[k]
            a = ab[int(t[1])]
            want = np.sqrt(a) * target.double().numpy() + np.sqrt(1 - a) * noise.double().numpy()
            np.testing.assert_allclose(x_t[1:][..., :4].numpy(), want[..., :4], rtol=1e-5, atol=1e-5)
        assert not torch.allclose(out[..., :4], target[..., :4])  # the free steps move off it
        # the unmasked half runs as it would: it depends on its own rows only (a per-pixel model)
        torch.testing.assert_close(out[..., 4:], free[..., 4:], rtol=0, atol=0)
    full = sample.ddim_clip(Shrink(CFG), conds, first, steps=steps, noise=noise, held=(target, mask), hold=steps)
    assert torch.equal(full[..., :4], target[..., :4])
    none = sample.ddim_clip(Shrink(CFG), conds, first, steps=steps, noise=noise,
                            held=(target, torch.zeros_like(mask)), hold=steps)
    assert torch.equal(none, free)
    with pytest.raises(ValueError, match="starting noise"):
        sample.ddim_clip(Shrink(CFG), conds, first, steps=steps, generator=g, held=(target, mask), hold=1)


def test_sequence_sampler_warps_each_clip_from_its_first_frame():
    """The warp is asked for the last generated frame (clean) into the clip's new frames; frame 1
    is the ACM's alone; hold = steps puts the targets in place; hold = 0 never calls it."""
    n, clip, steps = 7, 3, 4
    conds = torch.zeros(n, 3, 8, 8)
    calls = []

    def fake_warp(z, i, js):
        calls.append((z.clone(), i, list(js)))
        return torch.full((len(js), 3, 8, 8), float(i + 1)), torch.ones(len(js), 3, 8, 8)

    free = sample.sample_sequence(Shrink(CFG), Shrink(CFG), conds, steps=steps, seed=3, clip=clip)
    out = sample.sample_sequence(Shrink(CFG), Shrink(CFG), conds, steps=steps, seed=3, clip=clip,
                                 warp=fake_warp, hold=steps)
    assert [(i, js) for _, i, js in calls] == [(0, [1, 2]), (2, [3, 4]), (4, [5, 6])]
    assert torch.equal(out[0], free[0])
    assert torch.equal(calls[0][0], free[0])
    for i, js in ((0, [1, 2]), (2, [3, 4]), (4, [5, 6])):
        for j in js:
            assert torch.equal(out[j], torch.full((3, 8, 8), float(i + 1)))
    calls.clear()
    again = sample.sample_sequence(Shrink(CFG), Shrink(CFG), conds, steps=steps, seed=3, clip=clip,
                                   warp=fake_warp, hold=0)
    assert calls == [] and torch.equal(again, free)


def test_warp_targets_round_trip_under_a_still_camera():
    """Same camera and depth: the target is the frame itself in model space (decode, warp,
    encode, residual from the new frame's condition), through a patch fold and a residual."""
    cfg = core.CoreConfig(resolution=8, patch=2, conditioning="concat", residual=True, residual_scale=2.0, coords=True)
    g = torch.Generator().manual_seed(1)
    imgs = torch.rand(2, 3, 8, 8, generator=g) * 0.8 + 0.1
    cc = core.encode_cond(imgs, cfg)
    want = torch.rand(1, 3, 8, 8, generator=g) * 0.8 + 0.1
    z = core.to_diffused(core.encode(want, cfg), cc[:1], cfg)[0]
    cam = _cam(size=8)
    depth = np.full((8, 8), 5.0)
    targets, masks = warp.WarpTargets(cc, [depth, depth], [cam, cam], cfg)(z, 0, [1])
    assert masks.shape == (1, 12, 4, 4) and bool((masks == 1).all())
    back = core.decode(core.from_diffused(targets, cc[1:2], cfg), cfg)
    torch.testing.assert_close(back, want, rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match="depths"):
        warp.WarpTargets(cc, [depth], [cam, cam], cfg)


def test_prior_depth_of_an_opaque_plane():
    """A wall of small opaque Gaussians 6 m ahead: planar depth 6 where it covers the pixel, +inf
    (a direction) where nothing does, at the asked size with the intrinsics scaled to it."""
    xs, ys = np.meshgrid(np.linspace(-3, 3, 61), np.linspace(-3, 0, 31))
    xyz = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 6.0)], -1)  # the upper half of the view
    model = GaussianModel.from_points(xyz, np.full_like(xyz, 0.5), 0, opacity=0.99)
    scene = object()
    prior = types.SimpleNamespace(scene_model=lambda s: (model,) if s is scene else None,
                                  config=types.SimpleNamespace(sh_degree=0, render_near_m=0.1))
    frame = types.SimpleNamespace(camera=lambda: _cam(size=32, fov=40.0))
    depth = warp.prior_depth(prior, scene, frame, 16, 12)
    assert depth.shape == (12, 16)
    np.testing.assert_allclose(depth[1:5, 3:13], 6.0, rtol=1e-3)  # the wall (y < 0 is up)
    assert np.isinf(depth[8:]).all()  # below it: nothing


def test_skyeyes_checks_vcm_warp(tmp_path):
    from reference.methods.skyeyes import PRESETS, Skyeyes

    smoke = PRESETS["smoke"]
    with pytest.raises(ValueError, match="vcm_warp"):
        Skyeyes(dataclasses.replace(smoke, vcm_warp=smoke.sample_steps + 1), tmp_path)
    with pytest.raises(ValueError, match="vcm_warp"):
        Skyeyes(dataclasses.replace(smoke, vcm=False, vcm_warp=2), tmp_path)
    Skyeyes(dataclasses.replace(smoke, vcm_warp=smoke.sample_steps), tmp_path)


def test_without_a_vcm_each_frame_is_held_by_the_previous_one():
    """`vcm` None (1-frame clips): the ACM frame by frame in order; unheld, the frame sampler's
    frames (the same noise); held, each frame asks for the previous frame's warp alone."""
    n, steps = 5, 4
    conds = torch.zeros(n, 3, 6, 6)
    frames = sample.sample_frames(Shrink(CFG), conds, steps=steps, seed=9)
    seq = sample.sample_sequence(Shrink(CFG), None, conds, steps=steps, seed=9)
    torch.testing.assert_close(seq, frames, rtol=0, atol=1e-6)
    calls = []

    def fake_warp(z, i, js):
        calls.append((i, list(js)))
        return z[None] + 1.0, torch.ones(1, 3, 6, 6)

    held = sample.sample_sequence(Shrink(CFG), None, conds, steps=steps, seed=9, warp=fake_warp, hold=steps)
    assert calls == [(i, [i + 1]) for i in range(n - 1)]
    for i in range(1, n):
        torch.testing.assert_close(held[i], held[i - 1] + 1.0, rtol=0, atol=1e-6)


def test_frame_by_frame_methods_keep_the_vcm_fields_at_their_defaults():
    """The methods without a VCM keep the fields that mean nothing to them at the dataclass
    defaults, so their configs (and filed rows) do not follow Skyeyes' VCM settings."""
    from reference.methods import get_method_class
    from reference.common.diffusion.config import VCM_ONLY, DiffusionConfig, frame_by_frame
    from reference.methods.skyeyes import PRESETS

    defaults = {f.name: f.default for f in dataclasses.fields(DiffusionConfig)}
    warped = dataclasses.replace(PRESETS["small"], clip_frames=2, vcm_local=5, vcm_warp=9, vcm_keys="previous")
    plain = frame_by_frame(warped)
    assert not plain.vcm and {k: getattr(plain, k) for k in VCM_ONLY} == {k: defaults[k] for k in VCM_ONLY}
    assert plain.acm_steps == warped.acm_steps and plain.vcm_steps == warped.vcm_steps  # nothing else moves
    for name in ("skyeyes-no-vcm", "controlnet", "ip2p", "gvg"):
        for preset in ("smoke", "small", "paper"):
            cfg = get_method_class(name).presets[preset]
            assert not cfg.vcm, (name, preset)
            assert {k: getattr(cfg, k) for k in VCM_ONLY} == {k: defaults[k] for k in VCM_ONLY}, (name, preset)


def _still(depths, size=24):
    """The transfer's coordinates for a still camera over `depths` (one per frame)."""
    return warp.depth_coords(depths, [_cam(size=size)] * len(depths))


def test_lowpass_transfer_carries_the_coarse_part_and_keeps_the_detail():
    """A still camera: frame j's output is its own detail (image minus its Gaussian low-pass,
    scipy's) on the low-pass of output j - 1, so flat frames all take frame 0's colour and a
    checkerboard riding on them stays each frame's own; mix 1/2 goes half way."""
    size, sigma = 24, 3.0
    depth = np.full((size, size), 5.0)
    colours = torch.tensor([0.2, 0.5, 0.8])[:, None, None, None]  # frame j: grey level colours[j]
    checker = torch.as_tensor(np.indices((size, size)).sum(0) % 2 * 0.1 - 0.05, dtype=torch.float32)
    imgs = (colours.expand(3, 3, size, size) + checker * torch.tensor([0.0, 1.0, -1.0])[:, None, None, None])
    out = warp.lowpass_transfer(imgs, _still([depth] * 3, size), sigma)
    torch.testing.assert_close(out[0], imgs[0])
    low = ndimage.gaussian_filter(imgs.numpy(), (0, 0, sigma, sigma), mode="reflect")
    for j in (1, 2):
        want = imgs[j].numpy() - low[j] + ndimage.gaussian_filter(out[j - 1].numpy(), (0, sigma, sigma),
                                                                   mode="reflect")
        np.testing.assert_allclose(out[j].numpy(), want, atol=1e-5)
    assert abs(out[2].mean().item() - 0.2) < 1e-3  # frame 0's grey, carried twice
    np.testing.assert_allclose((out[2] - out[2].mean()).numpy(), -checker.expand(3, -1, -1).numpy(), atol=2e-2)
    half = warp.lowpass_transfer(imgs[:2], _still([depth] * 2, size), sigma, mix=0.5)
    assert abs(half[1].mean().item() - 0.35) < 1e-3


def test_lowpass_transfer_leaves_what_the_warp_does_not_reach():
    """Where the previous frame's depth disagrees (right half: 8 m against 5 m) the warp reaches
    nothing: those pixels, a ramp's width from the edge, are the frame's own; the left half's
    far side takes the previous colour; flat frames outside [0, 1] stay clamped."""
    size, sigma = 24, 1.0
    here = np.full((size, size), 5.0)
    before = here.copy()
    before[:, size // 2:] = 8.0
    imgs = torch.stack([torch.full((3, size, size), 0.9), torch.full((3, size, size), 0.1)])
    out = warp.lowpass_transfer(imgs, _still([before, here], size), sigma)
    np.testing.assert_allclose(out[1, :, :, size // 2:].numpy(), 0.1, atol=1e-6)
    np.testing.assert_allclose(out[1, :, :, : size // 2 - 4].numpy(), 0.9, atol=1e-3)
    with pytest.raises(ValueError, match="mix"):
        warp.lowpass_transfer(imgs, _still([before, here], size), sigma, mix=0.0)


def test_skyeyes_checks_vcm_lowpass(tmp_path):
    from reference.methods.skyeyes import PRESETS, Skyeyes

    smoke = PRESETS["smoke"]
    for bad in (dict(vcm_lowpass=-1.0), dict(vcm_lowpass=2.0, vcm_lowpass_mix=1.5), dict(vcm=False, vcm_lowpass=2.0)):
        with pytest.raises(ValueError, match="vcm_lowpass"):
            Skyeyes(dataclasses.replace(smoke, **bad), tmp_path)
    Skyeyes(dataclasses.replace(smoke, vcm_lowpass=2.0, vcm_lowpass_mix=0.5), tmp_path)


def _shift(h: int, w: int, dx: int, valid_cols: slice = slice(None)):
    """coords for every j: frame j - 1 seen from frame j is `dx` pixels to the right (a pan),
    valid in `valid_cols` of frame j."""
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    valid = np.zeros((h, w), bool)
    valid[:, valid_cols] = True
    return lambda j: (np.stack([xs + dx, ys], -1), valid)


def test_carried_noise_moves_with_the_picture_and_is_fresh_where_nothing_comes():
    """A pan of 2 pixels a frame: with share 1, frame j's noise is frame j - 1's shifted by 2
    (numpy's roll, on the columns the flow reaches) and its own draw in the last 2 columns, which
    the flow leaves; with share s the closed form sqrt(s) prev + sqrt(1 - s) own; over many
    draws every pixel stays N(0, 1)."""
    n, h, w = 4, 5, 12
    own = torch.randn(n, 3, h, w, generator=torch.Generator().manual_seed(0))
    out = warp.carried_noise(own, _shift(h, w, 2, slice(0, w - 2)), 1.0)
    torch.testing.assert_close(out[0], own[0])
    for j in range(1, n):
        np.testing.assert_array_equal(out[j, :, :, : w - 2].numpy(), np.roll(out[j - 1].numpy(), -2, axis=-1)[..., : w - 2])
        torch.testing.assert_close(out[j, :, :, w - 2:], own[j, :, :, w - 2:])
    s = 0.7
    half = warp.carried_noise(own, _shift(h, w, 2, slice(0, w - 2)), s)
    want = s ** 0.5 * np.roll(half[0].numpy(), -2, axis=-1) + (1 - s) ** 0.5 * own[1].numpy()
    np.testing.assert_allclose(half[1, :, :, : w - 2].numpy(), want[..., : w - 2], atol=1e-6)
    many = torch.stack([warp.carried_noise(torch.randn(n, 1, h, w, generator=torch.Generator().manual_seed(k)),
                                           _shift(h, w, 1, slice(0, w - 1)), s) for k in range(400)])
    assert abs(float(many[:, -1].var()) - 1.0) < 0.08 and abs(float(many[:, -1].mean())) < 0.05
    # the carried pixel of frame 3 against frame 2's pixel it came from: correlation sqrt(s)
    a, b = many[:, 3, 0, :, 0].flatten().numpy(), many[:, 2, 0, :, 1].flatten().numpy()
    assert abs(np.corrcoef(a, b)[0, 1] - s ** 0.5) < 0.08
    with pytest.raises(ValueError, match="coordinates"):
        warp.carried_noise(own, _shift(h, w + 1, 2), 1.0)


def test_skyeyes_checks_vcm_noise(tmp_path):
    from reference.methods.skyeyes import PRESETS, Skyeyes

    smoke = PRESETS["smoke"]
    for bad in (dict(vcm_noise=1.5), dict(vcm_noise=0.5, vcm_noise_sigma=-1.0), dict(vcm=False, vcm_noise=0.5),
                dict(vcm_noise=0.5, vcm_noise_flow=True, vcm_noise_sigma=2.0)):
        with pytest.raises(ValueError, match="vcm_noise"):
            Skyeyes(dataclasses.replace(smoke, **bad), tmp_path)
    Skyeyes(dataclasses.replace(smoke, vcm_noise=0.5, vcm_noise_flow=True), tmp_path)


def test_carried_noise_splits_a_sample_that_spreads_and_stays_white():
    """A 2x zoom along x (pixels 2m and 2m + 1 of frame j both come from pixel m of frame j - 1):
    with share 1 each pair's sum over sqrt(2) is the carried sample exactly, and over many draws
    the two pixels of a pair are uncorrelated N(0, 1) (copying the sample to both would correlate
    them fully)."""
    h, w = 3, 8
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    zoom = lambda j: (np.stack([xs / 2.0, ys], -1), np.ones((h, w), bool))  # noqa: E731
    out = warp.carried_noise(torch.randn(2, 2, h, w, generator=torch.Generator().manual_seed(1)), zoom, 1.0)
    np.testing.assert_allclose(((out[1, :, :, 0::2] + out[1, :, :, 1::2]) / 2 ** 0.5).numpy(),
                               out[0, :, :, : w // 2].numpy(), atol=1e-6)
    pairs = torch.stack([warp.carried_noise(torch.randn(2, 1, h, w, generator=torch.Generator().manual_seed(k)),
                                            zoom, 0.8)[1, 0] for k in range(600)])
    a, b = pairs[:, :, 0::2].flatten().numpy(), pairs[:, :, 1::2].flatten().numpy()
    assert abs(a.var() - 1.0) < 0.08 and abs(b.var() - 1.0) < 0.08
    assert abs(np.corrcoef(a, b)[0, 1]) < 0.06


def test_grid_coords_takes_the_fine_pixel_at_each_grid_centre():
    """Flow computed on an image 3 times the grid's size (grids under DIS's 12 pixels): grid pixel
    (r, c) takes the fine pixel (3r + 1, 3c + 1)'s coordinates over 3, which for a fine pan of 6
    pixels is a grid pan of 2, and its validity."""
    f, h, w = 3, 4, 5
    xs, ys = np.meshgrid(np.arange(w * f) + 0.5, np.arange(h * f) + 0.5)
    valid = np.ones((h * f, w * f), bool)
    valid[:, -6:] = False
    uv, v = warp.grid_coords(lambda j: (np.stack([xs + 6, ys], -1), valid), f)(1)
    gx, gy = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    np.testing.assert_allclose(uv, np.stack([gx + 2, gy], -1))
    np.testing.assert_array_equal(v, np.arange(w)[None].repeat(h, 0) < w - 2)
    same = lambda j: (xs, valid)  # noqa: E731
    assert warp.grid_coords(same, 1) is same


def test_affine_colours_recovers_an_exact_affine_map():
    """dst = M src + b on every pixel: the fitted map gives dst back (to rounding)."""
    g = torch.Generator().manual_seed(1)
    src = torch.rand(3, 3, 8, 8, generator=g)
    m = torch.tensor([[0.8, 0.1, 0.0], [-0.2, 0.9, 0.1], [0.05, 0.0, 1.2]])
    b = torch.tensor([0.1, -0.05, 0.02])
    dst = torch.einsum("ij,njhw->nihw", m, src) + b[None, :, None, None]
    for tiles in (1, 2, 4):  # the cells' maps are all the one map, and their blend weights sum to 1
        np.testing.assert_allclose(warp.affine_colours(src, dst, tiles).numpy(), dst.numpy(), atol=1e-5)


def test_affine_colours_on_a_grid_follows_a_map_that_varies_over_the_screen():
    """A contrast that ramps from 0.5 to 1.5 across the screen: one map misses it by far more than
    a map a cell of a 4 x 4 grid, blended between the cells."""
    g = torch.Generator().manual_seed(2)
    src = torch.rand(2, 3, 32, 32, generator=g)
    gain = 0.5 + (torch.arange(32) + 0.5) / 32
    dst = src * gain
    one, grid = ((warp.affine_colours(src, dst, t) - dst).abs().mean().item() for t in (1, 4))
    assert grid < one / 4, (one, grid)


def test_monge_colours_recover_a_symmetric_map_and_match_any_covariance():
    """fit="monge": where dst = A src + b with A symmetric positive definite (the one case where
    that map is the least move), it gives dst back; for colours no affine map explains, its output
    has dst's mean and covariance exactly (numpy's), where a least-squares map shrinks the
    variance by as much as src fails to predict dst."""
    g = torch.Generator().manual_seed(3)
    src = torch.rand(4, 3, 16, 16, generator=g, dtype=torch.float64)
    q = torch.randn(3, 3, generator=g, dtype=torch.float64)
    a = q @ q.T + 0.3 * torch.eye(3, dtype=torch.float64)
    dst = torch.einsum("ij,njhw->nihw", a, src) + torch.tensor([0.1, -0.2, 0.05], dtype=torch.float64)[None, :, None, None]
    for tiles in (1, 3):
        np.testing.assert_allclose(warp.affine_colours(src, dst, tiles, fit="monge").numpy(), dst.numpy(), atol=1e-4)
    other = torch.rand(4, 3, 16, 16, generator=g, dtype=torch.float64) ** 2  # independent of src
    flat = lambda x: x.permute(0, 2, 3, 1).reshape(-1, 3).numpy()  # noqa: E731
    out, want = flat(warp.affine_colours(src, other, 1, fit="monge")), flat(other)
    np.testing.assert_allclose(out.mean(0), want.mean(0), atol=1e-12)
    np.testing.assert_allclose(np.cov(out.T), np.cov(want.T), atol=1e-6)
    assert flat(warp.affine_colours(src, other, 1)).var(0).max() < 0.05 * want.var(0).min()
    with pytest.raises(ValueError, match="fit"):
        warp.affine_colours(src, other, 1, fit="moments")


def test_affine_colours_fitted_on_low_passes_ignore_detail_only_the_source_has():
    """src = a smooth field + a checkerboard (nothing below a 3 px Gaussian away from the border),
    dst = 2 x the smooth field. Fitted on the pixels, the checkerboard in the regressor shrinks the
    gain (errors in variables); fitted on the 3 px low-passes (sigma=3) the gain is 2, so the
    mapped src's low-pass is dst's."""
    g = torch.Generator().manual_seed(4)
    smooth = ndimage.gaussian_filter(torch.rand(2, 3, 48, 48, generator=g, dtype=torch.float64).numpy(),
                                     (0, 0, 6, 6), mode="reflect")
    smooth = torch.from_numpy((smooth - smooth.mean()) * 8)
    checker = torch.from_numpy(((np.indices((48, 48)).sum(0) % 2) * 2 - 1).astype(np.float64)) * 0.3
    src, dst = smooth + checker + 0.5, 2 * smooth + 0.4
    low = lambda x: ndimage.gaussian_filter(x.numpy(), (0, 0, 3, 3), mode="reflect")[..., 14:-14, 14:-14]  # noqa: E731
    fitted = warp.affine_colours(src, dst, 1, sigma=3.0)
    np.testing.assert_allclose(low(fitted), low(dst), atol=0.01)
    pixels = np.abs(low(warp.affine_colours(src, dst, 1)) - low(dst)).mean()
    assert pixels > 10 * np.abs(low(fitted) - low(dst)).mean(), pixels


def test_anchored_takes_the_targets_low_pass_and_keeps_the_detail():
    """A checkerboard (no energy below a Gaussian of 3 px: its low-pass is 0 to 1e-19 away from
    the border, where the reflection breaks it) on 0.5, anchored with mix 1 to a flat 0.3, is the
    same checkerboard on 0.3; with mix 0.5, on 0.4."""
    size, inner = 48, slice(14, -14)
    checker = torch.from_numpy(((np.indices((size, size)).sum(0) % 2) * 2 - 1).astype(np.float32)) * 0.2
    x = (0.5 + checker).expand(1, 3, size, size)
    flat = torch.full((1, 3, size, size), 0.3)
    for mix, level in ((1.0, 0.3), (0.5, 0.4)):
        got = warp.anchored(x, flat, 3.0, mix)[..., inner, inner]
        np.testing.assert_allclose(got.numpy(), (level + checker[inner, inner]).expand_as(got).numpy(), atol=1e-6)


def test_prior_anchor_removes_a_flicker_the_renders_do_not_have():
    """Frames that are an affine map of their renders plus a per-frame offset summing to 0 over
    the sequence (the renders are one image rolled, so every frame has the same colour sums and
    the offsets do not bias the fit): the anchor with mix 1 gives the mapped renders exactly, with
    mix 0.5 half the offsets; the renders' own motion (the roll) is kept."""
    from scipy.ndimage import gaussian_filter

    size, n = 32, 4
    base = gaussian_filter(np.random.default_rng(0).random((3, size, size)), (0, 2, 2), mode="wrap")
    renders = torch.from_numpy(np.stack([np.roll(base, 3 * k, axis=2) for k in range(n)]).astype(np.float32))
    mapped = 0.2 + 0.6 * renders.flip(1)  # a channel swap and a contrast change
    offsets = torch.tensor([0.05, -0.03, 0.02, -0.04])[:, None, None, None]
    frames = mapped + offsets
    np.testing.assert_allclose(warp.prior_anchor(frames, renders, 3.0).numpy(), mapped.numpy(), atol=1e-5)
    np.testing.assert_allclose(warp.prior_anchor(frames, renders, 3.0, 0.5).numpy(),
                               (mapped + offsets / 2).numpy(), atol=1e-5)
    with pytest.raises(ValueError, match="mix"):
        warp.prior_anchor(frames, renders, 3.0, 0.0)


def test_skyeyes_checks_vcm_anchor(tmp_path):
    from reference.methods.skyeyes import PRESETS, Skyeyes

    smoke = PRESETS["smoke"]
    for bad in (dict(vcm_anchor=-1.0), dict(vcm_anchor=2.0, vcm_anchor_mix=0.0), dict(vcm_anchor=2.0, vcm_anchor_tiles=0),
                dict(vcm=False, vcm_anchor=2.0), dict(vcm_anchor=2.0, condition="aerial")):
        with pytest.raises(ValueError, match="vcm_anchor"):
            Skyeyes(dataclasses.replace(smoke, **bad), tmp_path)
    Skyeyes(dataclasses.replace(smoke, vcm_anchor=2.0, vcm_anchor_mix=0.5), tmp_path)


@pytest.mark.parametrize("name", ["vcm_street", "vcm_sky"])
def test_skyeyes_checks_vcm_street_and_sky(tmp_path, name):
    from reference.methods.skyeyes import PRESETS, Skyeyes

    smoke = PRESETS["smoke"]
    for bad in ({name: -0.1}, {name: 1.5}, {name: 1.0, "vcm": False},
                {name: 1.0, "condition": "aerial"}, {name: 1.0, "prior_method": "mvs"}):
        with pytest.raises(ValueError, match=name):
            Skyeyes(dataclasses.replace(smoke, **bad), tmp_path)
    Skyeyes(dataclasses.replace(smoke, **{name: 1.0}), tmp_path)


def test_prior_ground_is_the_street_under_the_cameras_among_the_gaussians():
    """Gaussians of a street at z = 0.1 (sd 0.05 m), a few floaters under it and facades up to
    20 m; cameras 2 m up: the street's height is the mode of what lies under the cameras (0.05
    with `street_height`'s 0.1 m bins smoothed over 0.5 m), where the lower half's mode (a fused
    cloud's rule) would put it 0.25 m low, under the road."""
    rng = np.random.default_rng(0)
    z = np.concatenate([0.1 + rng.normal(0, 0.05, 4000), rng.uniform(-0.5, 0.1, 300), rng.uniform(0.0, 20.0, 4000)])
    xyz = np.zeros((len(z), 3))
    xyz[:, 2] = z
    model = GaussianModel.from_points(xyz, np.full_like(xyz, 0.5), 0)
    cam = _cam()
    cam.c2w[2, 3] = 2.0
    scene = types.SimpleNamespace(ground=[types.SimpleNamespace(camera=lambda: cam)])
    prior = types.SimpleNamespace(scene_model=lambda s: (model,))
    assert abs(warp.prior_ground(prior, scene) - 0.1) <= 0.06


def _shift_coords(dx: int, size: int):
    """j -> (uv, valid): frame j - 1 seen from frame j when the picture moved `dx` whole pixels to
    the right (pixel x of frame j shows pixel x - dx of frame j - 1), valid where that lands inside."""
    xs, ys = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)
    uv = np.stack([xs - dx, ys], -1)
    return lambda j: (uv, (uv[..., 0] > 0) & (uv[..., 0] < size))


def test_flow_align_moves_the_frame_and_puts_it_on_the_next_condition():
    """A whole-pixel shift: frame j's view of frame i is frame i rolled by the shift (a closed
    form: np.roll), frame i's own pixels where the shift brings nothing, expressed as a residual
    from frame j's condition (through a patch fold and a residual scale); neighbours only."""
    cfg = core.CoreConfig(resolution=8, patch=2, conditioning="concat", residual=True, residual_scale=2.0, coords=True)
    g = torch.Generator().manual_seed(2)
    cc = core.encode_cond(torch.rand(2, 3, 8, 8, generator=g), cfg)
    img = torch.rand(1, 3, 8, 8, generator=g) * 0.8 + 0.1
    z = core.to_diffused(core.encode(img, cfg), cc[:1], cfg)[0]
    out = warp.FlowAlign(cc, _shift_coords(2, 8), cfg)(z, 0, 1)
    assert out.shape == z.shape
    got = core.decode(core.from_diffused(out[None], cc[1:2], cfg), cfg)[0].numpy()
    want = np.roll(img[0].numpy(), 2, axis=-1)
    want[..., :2] = img[0].numpy()[..., :2]  # nothing comes there: frame i's own pixels
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match="neighbours"):
        warp.FlowAlign(cc, _shift_coords(2, 8), cfg)(z, 0, 2)


class CondShrink(Shrink):
    """`Shrink` that also records its conditions."""

    def forward(self, x_t, t, cond=None):
        self.conds = getattr(self, "conds", []) + [cond.clone()]
        return super().forward(x_t, t, cond)


def test_sequence_sampler_gives_the_vcm_the_aligned_frame_before_on_the_next_condition():
    """With `align`, each 2-frame clip's clean first frame is align(the frame just generated, i -
    1, i), entering on frame i's condition; the output keeps the generated frames themselves, and
    frame 0 is the ACM's alone as without it."""
    n, steps = 4, 4
    conds = torch.arange(n, dtype=torch.float32)[:, None, None, None].expand(n, 3, 8, 8).contiguous()
    calls = []

    def fake_align(z, i, j):
        calls.append((z.clone(), i, j))
        return z + 100.0 * (i + 1)

    free = sample.sample_sequence(Shrink(CFG), Shrink(CFG), conds, steps=steps, seed=5, clip=2)
    vcm_model = CondShrink(CFG)
    out = sample.sample_sequence(Shrink(CFG), vcm_model, conds, steps=steps, seed=5, clip=2, align=fake_align)
    assert [(i, j) for _, i, j in calls] == [(0, 1), (1, 2), (2, 3)]
    assert torch.equal(out[0], free[0])
    for k, (z, i, _) in enumerate(calls):
        assert torch.equal(z, out[i])  # the generated frame, not its aligned copy
        first_in, t_in = vcm_model.calls[k * steps]
        assert torch.equal(first_in[0], out[i] + 100.0 * (i + 1)) and int(t_in[0]) == 0
        assert torch.equal(vcm_model.conds[k * steps][0], conds[i + 1])  # both frames on frame i + 1's condition
        assert torch.equal(vcm_model.conds[k * steps][1], conds[i + 1])


def test_aligned_training_pairs_are_the_frame_before_moved_into_each_frame(monkeypatch):
    """`stages.aligned_firsts`: row j is row j - 1 of its sequence moved by the conditions' flow
    (here a whole-pixel shift standing in for it) and re-expressed on row j's condition; a
    sequence's first row is zero."""
    from reference.common.diffusion import stages

    cfg = core.CoreConfig(resolution=8, patch=2, conditioning="concat", residual=True, residual_scale=2.0, coords=True)
    g = torch.Generator().manual_seed(3)
    renders = torch.rand(5, 3, 8, 8, generator=g)
    imgs = torch.rand(5, 3, 8, 8, generator=g) * 0.8 + 0.1
    cc = core.encode_cond(renders, cfg)
    d = stages.TrainSet(list(range(5)), core.to_diffused(core.encode(imgs, cfg), cc, cfg), cc, "", "")
    seen = []

    def fake_flow(guides, **kw):
        seen.append(guides)
        return _shift_coords(1, 8)

    monkeypatch.setattr(warp, "flow_coords", fake_flow)
    out = stages.aligned_firsts(d, [[0, 1, 2], [3, 4]], cfg)
    # the flow is computed on the conditions' colours (the renders), a sequence at a time
    np.testing.assert_allclose(seen[1], renders[3:].permute(0, 2, 3, 1).numpy(), atol=1e-6)
    assert torch.equal(out[0], torch.zeros_like(out[0])) and torch.equal(out[3], torch.zeros_like(out[3]))
    for j in (1, 2, 4):
        got = core.decode(core.from_diffused(out[j:j + 1], cc[j:j + 1], cfg), cfg)[0].numpy()
        want = np.roll(imgs[j - 1].numpy(), 1, axis=-1)
        want[..., :1] = imgs[j - 1].numpy()[..., :1]
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-5)


def _street(n: int = 5, size: int = 24, step: float = 0.8):
    """A camera 2 m over the plane z = 0 (world z up), looking level along +x and moving `step` m
    a frame, over a smooth ground texture under a smooth sky; each frame's colours off by its own
    constant (a flicker). -> (frames [N, 3, H, W], cameras, offsets [N], ground(x, y), sky(dirs))."""
    rot = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # camera x, y, z -> world -y, -z, +x
    cams = []
    for k in range(n):
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = rot, [k * step, 0.0, 2.0]
        cams.append(Camera(intrinsics(70.0, size, size), c2w, size, size))

    def ground(x, y):
        return np.stack([0.4 + 0.1 * np.sin(0.4 * x), 0.3 + 0.1 * np.cos(0.5 * y), 0.35 + 0.05 * np.sin(0.3 * (x + y))], -1)

    def sky(d):
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        return np.stack([0.5 + 0.2 * d[..., 2], 0.6 + 0.1 * d[..., 1], 0.8 - 0.1 * d[..., 2]], -1)

    offsets = np.array([0.0, 0.06, -0.04, 0.08, -0.02, 0.05, 0.0][:n])
    frames = []
    for cam, c in zip(cams, offsets):
        o, d = cam.rays(normalize=False)
        t = np.where(d[:, 2] < 0, -o[:, 2] / np.where(d[:, 2] < 0, d[:, 2], -1.0), np.inf)
        p = o + d * np.where(np.isfinite(t), t, 0.0)[:, None]
        col = np.where(np.isfinite(t)[:, None], ground(p[:, 0], p[:, 1]), sky(d)) + c
        frames.append(col.reshape(size, size, 3).transpose(2, 0, 1))
    return torch.tensor(np.stack(frames), dtype=torch.float32), cams, offsets, ground, sky


def test_street_points_are_the_plane_under_the_horizon_before_the_prior():
    """Level camera 2 m up: a pixel is street when its ray meets the plane (at planar depth 2 /
    the ray's fall) nearer than `far` and not behind the prior's surface (or where the prior has
    nothing); the points lie on the plane."""
    _, cams, _, _, _ = _street(n=1)
    cam = cams[0]
    _, d = cam.rays(normalize=False)
    depth = np.full((24, 24), np.inf)
    depth[20:, :6] = 1.0  # something of the prior's in front of the near street
    pts, t, street = warp.street_points(cam, depth, 0.0, far=12.0)
    fall = -d[:, 2]
    want_t = np.where(fall > 0, 2.0 / np.where(fall > 0, fall, 1.0), np.inf)
    np.testing.assert_allclose(t, want_t, rtol=1e-12)
    np.testing.assert_array_equal(street, (want_t < 12.0) & (want_t <= depth.ravel() * (1 + warp.DEPTH_TOL)))
    assert street.reshape(24, 24)[20:, :6].sum() == 0 and street.reshape(24, 24)[20:, 6:].all()
    assert not street.reshape(24, 24)[:12].any()  # at and above the horizon: no street
    np.testing.assert_allclose(pts[street][:, 2], 0.0, atol=1e-9)


def _owner_reference(cams, p, h, w, far, view_m):
    """The frame whose view of street point p is chosen (a slow loop with `Camera.project`): the
    one that sees it within its pixel centres, as street at the nearest pixel, at the planar
    depth nearest view_m (0: the nearest)."""
    best, owner = np.inf, None
    for s, cam in enumerate(cams):
        uv, z = cam.project(p[None])
        u, v = uv[0]
        if z[0] > 0 and 0.5 <= u <= w - 0.5 and 0.5 <= v <= h - 0.5:
            _, ds = cam.rays(np.array([[np.floor(u) + 0.5, np.floor(v) + 0.5]]), normalize=False)
            key = abs(z[0] - view_m) if view_m else z[0]
            if -2.0 / min(ds[0, 2], -1e-12) < far and key < best:
                best, owner = key, s
    return owner


@pytest.mark.parametrize("view_m", [0.0, 6.0])
def test_street_transfer_takes_each_point_from_one_view(view_m):
    """A camera driving over a textured street, each frame off by its own constant: a street pixel
    becomes the texture plus the offset of the frame that sees its point at the depth nearest
    `view_m` (`_owner_reference`); above the street nothing changes; the warp error between
    frames (the metric's own warp, by the true depth) falls to the texture's resampling error."""
    from skyeyes_bench.metrics.geometry import warp_coords, warp_error

    imgs, cams, offsets, ground, _ = _street()
    n, _, h, w = imgs.shape
    depths = [np.full((h, w), np.inf)] * n
    out = warp.street_transfer(imgs, cams, depths, 0.0, far=12.0, view_m=view_m).numpy()
    x = imgs.numpy()
    owners = set()
    for k in (0, 2):
        o, d = cams[k].rays(normalize=False)
        fall = np.where(d[:, 2] < 0, -d[:, 2], 0.0)
        street = ((fall > 0) & (2.0 < 12.0 * fall)).reshape(h, w)
        np.testing.assert_array_equal(out[k][:, ~street], x[k][:, ~street])
        for i in range(h * w):
            r, c = divmod(i, w)
            if r in (0, h - 1) or c in (0, w - 1) or not street[r - 1:r + 2, c - 1:c + 2].all():
                continue  # the ramp's border pixels
            p = o[i] + d[i] * (2.0 / fall[i])
            owner = _owner_reference(cams, p, h, w, 12.0, view_m)
            owners.add(owner)
            np.testing.assert_allclose(out[k, :, r, c], np.clip(ground(p[0], p[1]) + offsets[owner], 0, 1), atol=0.02)
    assert len(owners) >= 3  # the points come from several views
    before = after = 0.0
    for k in range(n - 1):
        depth = []
        for cam in (cams[k + 1], cams[k]):
            _, d = cam.rays(normalize=False)
            depth.append(np.where(d[:, 2] < 0, -2.0 / np.where(d[:, 2] < 0, d[:, 2], -1.0), np.inf).reshape(h, w))
        uv, ok = warp_coords(depth[0], cams[k + 1], depth[1], cams[k], 0.01)
        ok &= (depth[0] < 12.0)  # the street the transfer covers
        before += warp_error(x[k].transpose(1, 2, 0), x[k + 1].transpose(1, 2, 0), uv, ok)[0]
        after += warp_error(out[k].transpose(1, 2, 0), out[k + 1].transpose(1, 2, 0), uv, ok)[0]
    assert before / (n - 1) > 0.04 and after < 0.3 * before  # what is left: the ramps, resampling
    half = warp.street_transfer(imgs, cams, depths, 0.0, far=12.0, view_m=view_m, mix=0.5).numpy()
    np.testing.assert_allclose(half, 0.5 * (x + out), atol=1e-5)
    with pytest.raises(ValueError, match="mix"):
        warp.street_transfer(imgs, cams, depths, 0.0, mix=0.0)


def test_street_transfer_leaves_what_the_prior_puts_in_front():
    """Pixels where the prior's surface stands before the plane (a wall, a car) are not street:
    they keep their own colours exactly."""
    imgs, cams, _, _, _ = _street(n=3)
    depths = [np.full((24, 24), np.inf) for _ in cams]
    for dep in depths:
        dep[:, 10:14] = 3.0
    out = warp.street_transfer(imgs, cams, depths, 0.0, far=12.0)
    torch.testing.assert_close(out[..., 10:14], imgs[..., 10:14], rtol=0, atol=0)
    assert not torch.allclose(out[..., 16:, :8], imgs[..., 16:, :8])


def _sky_pixels(cam, depth):
    """[H, W] the pixels `sky_fit` treats as sky: nothing of the prior's, the ray above the horizon."""
    _, d = cam.rays()
    return (np.isinf(depth).ravel() & (d[:, 2] > 0)).reshape(depth.shape)


def test_sky_fit_is_one_function_of_the_direction_for_the_sequence():
    """A sky linear in the ray's direction, each frame off by its own constant (`_street`): with
    no trimming, the interior sky pixels of every frame become that sky plus the offsets' mean
    (the least squares of a degree 1 or 2 polynomial over the same directions in every frame);
    the street keeps its own colours exactly; the mask's border pixels go half the way; half the
    mix is half the way."""
    imgs, cams, offsets, _, sky = _street()
    n, _, h, w = imgs.shape
    depths = [np.full((h, w), np.inf) for _ in cams]
    mean = offsets.mean()  # the cameras only translate: every frame's sky pixels see the same directions
    for degree in (1, 2):
        out = warp.sky_fit(imgs, cams, depths, degree=degree, trim=0.0).numpy()
        for k, cam in enumerate(cams):
            m = _sky_pixels(cam, depths[k])
            inner = m & (ndimage.uniform_filter(m.astype(float), 3, mode="nearest") > 0.999)
            _, d = cam.rays()
            want = sky(d).reshape(h, w, 3) + mean
            np.testing.assert_allclose(out[k].transpose(1, 2, 0)[inner], want[inner], atol=1e-5)
            np.testing.assert_array_equal(out[k][:, ~m], imgs[k].numpy()[:, ~m])
            edge = m & ~inner
            np.testing.assert_allclose(out[k].transpose(1, 2, 0)[edge],
                                       0.5 * (imgs[k].numpy().transpose(1, 2, 0)[edge] + want[edge]), atol=1e-5)
    assert inner.sum() > 50
    half = warp.sky_fit(imgs, cams, depths, mix=0.5, trim=0.0).numpy()
    np.testing.assert_allclose(half, 0.5 * (imgs.numpy() + warp.sky_fit(imgs, cams, depths, trim=0.0).numpy()), atol=1e-5)
    for bad in (dict(mix=0.0), dict(mix=1.5), dict(degree=-1), dict(trim=1.0)):
        with pytest.raises(ValueError, match="sky_fit"):
            warp.sky_fit(imgs, cams, depths, **bad)
    with pytest.raises(ValueError, match="2 depths"):
        warp.sky_fit(imgs, cams, depths[:2])


def test_sky_fit_trims_a_ghost():
    """One frame paints a dark ghost over a few of its sky pixels (under a fifth of the
    sequence's): the trimmed fit is the true sky, exactly, in every frame, the ghost painted
    over, and the prior's building kept as it is; the untrimmed one is pulled towards the ghost."""
    imgs, cams, _, _, sky = _street(n=4)
    n, _, h, w = imgs.shape
    _, d = cams[0].rays()
    clean = torch.tensor(np.stack([sky(d).reshape(h, w, 3).transpose(2, 0, 1)] * n), dtype=torch.float32)
    ground = ~_sky_pixels(cams[0], np.full((h, w), np.inf))
    clean[:, :, ground] = imgs[:, :, ground]
    ghosted = clean.clone()
    ghosted[2, :, 3:7, 8:14] = 0.1
    depths = [np.full((h, w), np.inf) for _ in range(n)]
    depths[1][2:6, 4:9] = 20.0  # a building of the prior's against the sky: left as it is
    m = _sky_pixels(cams[0], depths[0])
    inner = m & (ndimage.uniform_filter(m.astype(float), 3, mode="nearest") > 0.999)
    assert 0 < 24 < 0.2 * n * m.sum()
    out = warp.sky_fit(ghosted, cams, depths).numpy()
    for k in range(n):
        keep = ~_sky_pixels(cams[k], depths[k])
        np.testing.assert_array_equal(out[k][:, keep], ghosted[k].numpy()[:, keep])
        ok = inner & ~ndimage.binary_dilation(keep, iterations=1)
        np.testing.assert_allclose(out[k][:, ok], clean[k].numpy()[:, ok], atol=1e-5)
    pulled = warp.sky_fit(ghosted, cams, depths, trim=0.0).numpy()
    assert np.abs(pulled[0][:, inner] - clean[0].numpy()[:, inner]).max() > 0.01


@pytest.mark.parametrize("street, sky, ground", [(0.8, 1.0, 0.25), (0.8, 0.0, 0.25), (0.0, 0.7, 0.25), (0.8, 1.0, None), (0.8, 0.0, None)])
def test_pipeline_takes_the_street_then_the_sky(tmp_path, monkeypatch, street, sky, ground):
    """`Skyeyes._street`: the prior's depth and the scaled cameras of every frame, then the street
    transfer at `vcm_street` (skipped when it is 0 or the prior has no street), then the sky fit at
    `vcm_sky` (skipped when 0), each on the one before's frames; with neither, no depth rendered."""
    from reference.methods.skyeyes import PRESETS, Skyeyes

    m = Skyeyes(dataclasses.replace(PRESETS["smoke"], vcm_street=street, vcm_sky=sky), tmp_path)
    m._prior = object()
    calls = []
    rendered = []
    monkeypatch.setattr(warp, "prior_depth", lambda prior, scene, f, w, h:
                        rendered.append(f) or np.full((h, w), float(f.camera())))
    monkeypatch.setattr(warp, "scaled_camera", lambda cam, w, h: ("cam", cam, w, h))
    monkeypatch.setattr(warp, "prior_ground", lambda prior, scene: ground)
    monkeypatch.setattr(warp, "street_transfer", lambda x, cams, depths, zg, *, mix:
                        calls.append(("street", [c[1] for c in cams], [d[0, 0] for d in depths], zg, mix)) or x + 1)
    monkeypatch.setattr(warp, "sky_fit", lambda x, cams, depths, *, mix:
                        calls.append(("sky", [c[1] for c in cams], [d[0, 0] for d in depths], mix)) or x * 2)
    frames = [7, 8, 9]  # each frame's camera, and its prior depth
    seq = types.SimpleNamespace(frames=[types.SimpleNamespace(camera=lambda k=k: k) for k in frames])
    imgs = torch.zeros(3, 3, 4, 5)
    out = m._street(types.SimpleNamespace(name="s"), seq, imgs)
    want, x = [], 0.0
    if street and ground is not None:
        want.append(("street", frames, [7.0, 8.0, 9.0], ground, street))
        x = x + 1
    if sky:
        want.append(("sky", frames, [7.0, 8.0, 9.0], sky))
        x = x * 2
    assert calls == want
    assert len(rendered) == (3 if want else 0)  # no depths rendered when there is nothing to take
    torch.testing.assert_close(out, torch.full_like(imgs, x))
