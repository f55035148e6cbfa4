"""Our additions to Skyeyes (`reference.common.diffusion.additions`, run only by `skyeyes-geo` and
`skyeyes-geo-no-vcm`): each step against a closed form or an independent computation (numpy,
scipy, a slow loop), each check of its assumption on a case that holds and one that does not,
the pipeline's order of the steps, and the paper's `skyeyes` held to the paper's components."""

from __future__ import annotations

import dataclasses
import types

import numpy as np
import pytest
import torch
from scipy import ndimage

from reference.common.diffusion.additions import (Additions, AdditionsConfig, CarriedNoiseConfig, PriorAnchor,
                                                  PriorAnchorConfig, SequenceView, SkyConfig, SkyFromOneFit,
                                                  StreetConfig, StreetFromOneView)
from reference.common.diffusion.additions.anchor import affine_colours, anchored, prior_anchor
from reference.common.diffusion.additions.noise import carried_noise
from reference.common.diffusion.additions.sky import sky_fit
from reference.common.diffusion.additions.street import (DEPTH_TOL, level_street, prior_ground, street_points,
                                                         street_transfer)
from reference.common.diffusion.additions.view import grid_coords, prior_depth
from reference.common.gaussians.scene_geometry import GaussianGeometry
from reference.common.diffusion.config import DiffusionConfig
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


# --------------------------------------------------------------------------- the configs


def test_additions_of_a_config_are_the_components_it_turns_on_in_order():
    """The paper's config (a plain `DiffusionConfig`) and an `AdditionsConfig` at its defaults turn
    on nothing; each config's mix (or share) above 0 turns on its component, the steps after
    sampling in the order anchor, street, sky; a value out of range is refused naming its field."""
    assert Additions.of(DiffusionConfig()).components == []
    assert Additions.of(AdditionsConfig()).components == []
    on = AdditionsConfig(noise=CarriedNoiseConfig(share=0.5), anchor=PriorAnchorConfig(mix=0.5),
                         street=StreetConfig(mix=0.8), sky=SkyConfig(mix=1.0))
    adds = Additions.of(on)
    assert adds.names == ["carried noise", "prior anchor", "street from one view", "sky from one fit"]
    assert adds.needs_gaussians
    assert Additions.of(dataclasses.replace(on, street=StreetConfig(), sky=SkyConfig())).needs_gaussians is False
    only_sky = Additions.of(AdditionsConfig(sky=SkyConfig(mix=0.3)))
    assert only_sky.noise is None and [type(s) for s in only_sky.post] == [SkyFromOneFit]
    for make, match in ((lambda: CarriedNoiseConfig(share=1.5), "noise.share"), (lambda: PriorAnchorConfig(mix=-0.1), "anchor"),
                        (lambda: PriorAnchorConfig(mix=0.5, tiles=0), "anchor"),
                        (lambda: StreetConfig(mix=0.5, max_tilt_deg=0.0), "street"),
                        (lambda: SkyConfig(mix=0.5, trim=1.0), "sky")):
        with pytest.raises(ValueError, match=match):
            make()


def test_frame_by_frame_methods_keep_the_vcm_fields_at_their_defaults():
    """The methods without a VCM keep the fields that mean nothing to them (`VCM_ONLY`) at the
    dataclass defaults, so their configs (and filed rows) do not follow Skyeyes' VCM settings;
    `frame_by_frame` moves nothing else, and keeps an `AdditionsConfig`'s additions."""
    from reference.common.diffusion.config import VCM_ONLY, frame_by_frame
    from reference.methods import get_method_class
    from reference.methods.skyeyes import PRESETS
    from reference.methods.skyeyes_geo import PRESETS as GEO

    defaults = {f.name: f.default for f in dataclasses.fields(DiffusionConfig)}
    other = dataclasses.replace(PRESETS["small"], clip_frames=2, vcm_local=5, vcm_keys="previous", vcm_crop=0,
                                vcm_levels=1, vcm_snr_gamma=2.0)
    plain = frame_by_frame(other)
    assert not plain.vcm and {k: getattr(plain, k) for k in VCM_ONLY} == {k: defaults[k] for k in VCM_ONLY}
    moved = {k for k, v in dataclasses.asdict(plain).items() if v != dataclasses.asdict(other)[k]}
    assert moved == {"vcm", *VCM_ONLY}  # nothing else moves
    geo = frame_by_frame(dataclasses.replace(GEO["small"], clip_frames=3))
    assert isinstance(geo, AdditionsConfig) and geo.clip_frames == defaults["clip_frames"]
    assert (geo.noise, geo.anchor, geo.street, geo.sky) == (GEO["small"].noise, GEO["small"].anchor,
                                                            GEO["small"].street, GEO["small"].sky)
    for name in ("skyeyes-no-vcm", "skyeyes-geo-no-vcm", "controlnet", "ip2p", "gvg"):
        for preset in ("smoke", "small", "paper"):
            cfg = get_method_class(name).presets[preset]
            assert not cfg.vcm, (name, preset)
            assert {k: getattr(cfg, k) for k in VCM_ONLY} == {k: defaults[k] for k in VCM_ONLY}, (name, preset)


# --------------------------------------------------------------------------- the paper's method


@pytest.mark.parametrize("preset", ["smoke", "small", "paper"])
def test_the_papers_skyeyes_runs_the_papers_components_and_nothing_of_ours(preset, tmp_path):
    """`skyeyes` at every preset is the paper's pipeline (`PAPER_COMPONENTS`: SuGaR's renders, the
    ACM, the VCM on 12-frame clips, pure Gaussian noise), on a plain `DiffusionConfig` that turns
    on none of our additions; its ablation differs from it in the VCM alone (`vcm` and the fields
    only the VCM reads), as `skyeyes-geo-no-vcm`
    does from `skyeyes-geo`, and `skyeyes-geo` is `skyeyes` in every field the family has."""
    from builders.skyeyes import StandInPrior
    from reference.methods.skyeyes import PAPER_COMPONENTS, PRESETS, Skyeyes, SkyeyesNoVCM
    from reference.methods.skyeyes_geo import SkyeyesGeo, SkyeyesGeoNoVCM

    cfg = PRESETS[preset]
    m = Skyeyes(cfg, tmp_path / "paper", prior_method=StandInPrior(tmp_path / "prior"), progress=False)
    assert cfg.clip_frames == 12  # NOTE: Skyeyes Sec. 3.3, "a consecutive of 12 frames"
    assert m.components() == list(PAPER_COMPONENTS)
    assert type(m.config) is DiffusionConfig and not isinstance(m.config, AdditionsConfig)
    assert Additions.of(m.config).components == [] and m.additions.components == []
    assert m.kind == "paper"

    def differs(a, b) -> set[str]:
        da, db = dataclasses.asdict(a), dataclasses.asdict(b)
        assert da.keys() == db.keys()
        return {k for k in da if da[k] != db[k]}

    # the VCM and the fields that are only the VCM's (its loss weights at `small`, chosen on val)
    from reference.common.diffusion.config import VCM_ONLY

    assert "vcm" in differs(Skyeyes.presets[preset], SkyeyesNoVCM.presets[preset]) <= {"vcm", *VCM_ONLY}
    assert "vcm" in differs(SkyeyesGeo.presets[preset], SkyeyesGeoNoVCM.presets[preset]) <= {"vcm", *VCM_ONLY}
    geo = SkyeyesGeo.presets[preset]
    for f in dataclasses.fields(DiffusionConfig):
        assert getattr(geo, f.name) == getattr(cfg, f.name), f.name
    g = SkyeyesGeo(geo, tmp_path / "geo", prior_method=StandInPrior(tmp_path / "prior"), progress=False)
    assert g.components()[:3] == list(PAPER_COMPONENTS[:3])
    # the validation split chose carried noise and the anchor at `small` (docs/skyeyes.md); smoke runs all four
    ours = {"smoke": ["carried noise", "prior anchor", "street from one view", "sky from one fit"],
            "small": ["carried noise", "prior anchor"], "paper": ["carried noise", "prior anchor"]}[preset]
    assert g.components()[3:] == ours


# --------------------------------------------------------------------------- carried noise


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
    out = carried_noise(own, _shift(h, w, 2, slice(0, w - 2)), 1.0)
    torch.testing.assert_close(out[0], own[0])
    for j in range(1, n):
        np.testing.assert_array_equal(out[j, :, :, : w - 2].numpy(), np.roll(out[j - 1].numpy(), -2, axis=-1)[..., : w - 2])
        torch.testing.assert_close(out[j, :, :, w - 2:], own[j, :, :, w - 2:])
    s = 0.7
    half = carried_noise(own, _shift(h, w, 2, slice(0, w - 2)), s)
    want = s ** 0.5 * np.roll(half[0].numpy(), -2, axis=-1) + (1 - s) ** 0.5 * own[1].numpy()
    np.testing.assert_allclose(half[1, :, :, : w - 2].numpy(), want[..., : w - 2], atol=1e-6)
    many = torch.stack([carried_noise(torch.randn(n, 1, h, w, generator=torch.Generator().manual_seed(k)),
                                      _shift(h, w, 1, slice(0, w - 1)), s) for k in range(400)])
    assert abs(float(many[:, -1].var()) - 1.0) < 0.08 and abs(float(many[:, -1].mean())) < 0.05
    # the carried pixel of frame 3 against frame 2's pixel it came from: correlation sqrt(s)
    a, b = many[:, 3, 0, :, 0].flatten().numpy(), many[:, 2, 0, :, 1].flatten().numpy()
    assert abs(np.corrcoef(a, b)[0, 1] - s ** 0.5) < 0.08
    assert torch.equal(carried_noise(own, _shift(h, w, 2), 0.0), own)  # share 0: every frame its own
    with pytest.raises(ValueError, match="coordinates"):
        carried_noise(own, _shift(h, w + 1, 2), 1.0)
    with pytest.raises(ValueError, match="share"):
        carried_noise(own, _shift(h, w, 2), 1.5)


def test_carried_noise_splits_a_sample_that_spreads_and_stays_white():
    """A 2x zoom along x (pixels 2m and 2m + 1 of frame j both come from pixel m of frame j - 1):
    with share 1 each pair's sum over sqrt(2) is the carried sample exactly, and over many draws
    the two pixels of a pair are uncorrelated N(0, 1) (copying the sample to both would correlate
    them fully)."""
    h, w = 3, 8
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    zoom = lambda j: (np.stack([xs / 2.0, ys], -1), np.ones((h, w), bool))  # noqa: E731
    out = carried_noise(torch.randn(2, 2, h, w, generator=torch.Generator().manual_seed(1)), zoom, 1.0)
    np.testing.assert_allclose(((out[1, :, :, 0::2] + out[1, :, :, 1::2]) / 2 ** 0.5).numpy(),
                               out[0, :, :, : w // 2].numpy(), atol=1e-6)
    pairs = torch.stack([carried_noise(torch.randn(2, 1, h, w, generator=torch.Generator().manual_seed(k)),
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
    uv, v = grid_coords(lambda j: (np.stack([xs + 6, ys], -1), valid), f)(1)
    gx, gy = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    np.testing.assert_allclose(uv, np.stack([gx + 2, gy], -1))
    np.testing.assert_array_equal(v, np.arange(w)[None].repeat(h, 0) < w - 2)
    same = lambda j: (xs, valid)  # noqa: E731
    assert grid_coords(same, 1) is same


# --------------------------------------------------------------------------- the prior anchor


def test_affine_colours_recovers_an_exact_affine_map():
    """dst = M src + b on every pixel: the fitted map gives dst back (to rounding)."""
    g = torch.Generator().manual_seed(1)
    src = torch.rand(3, 3, 8, 8, generator=g)
    m = torch.tensor([[0.8, 0.1, 0.0], [-0.2, 0.9, 0.1], [0.05, 0.0, 1.2]])
    b = torch.tensor([0.1, -0.05, 0.02])
    dst = torch.einsum("ij,njhw->nihw", m, src) + b[None, :, None, None]
    for tiles in (1, 2, 4):  # the cells' maps are all the one map, and their blend weights sum to 1
        np.testing.assert_allclose(affine_colours(src, dst, tiles).numpy(), dst.numpy(), atol=1e-5)


def test_affine_colours_is_numpys_least_squares():
    """For colours no affine map explains, one map (tiles 1) is numpy's least-squares fit of dst
    on [src, 1] over every pixel of every frame, applied to src."""
    g = torch.Generator().manual_seed(5)
    src = torch.rand(2, 3, 6, 7, generator=g, dtype=torch.float64)
    dst = torch.rand(2, 3, 6, 7, generator=g, dtype=torch.float64) ** 2 + 0.3 * src.flip(1)
    a = np.c_[src.permute(0, 2, 3, 1).reshape(-1, 3).numpy(), np.ones(2 * 6 * 7)]
    coef = np.linalg.lstsq(a, dst.permute(0, 2, 3, 1).reshape(-1, 3).numpy(), rcond=None)[0]
    want = (a @ coef).reshape(2, 6, 7, 3).transpose(0, 3, 1, 2)
    np.testing.assert_allclose(affine_colours(src, dst, 1).numpy(), want, atol=1e-10)


def test_affine_colours_on_a_grid_follows_a_map_that_varies_over_the_screen():
    """A contrast that ramps from 0.5 to 1.5 across the screen: one map misses it by far more than
    a map a cell of a 4 x 4 grid, blended between the cells."""
    g = torch.Generator().manual_seed(2)
    src = torch.rand(2, 3, 32, 32, generator=g)
    gain = 0.5 + (torch.arange(32) + 0.5) / 32
    dst = src * gain
    one, grid = ((affine_colours(src, dst, t) - dst).abs().mean().item() for t in (1, 4))
    assert grid < one / 4, (one, grid)


def test_anchored_takes_the_targets_low_pass_and_keeps_the_detail():
    """A checkerboard (no energy below a Gaussian of 3 px: its low-pass is 0 to 1e-19 away from
    the border, where the reflection breaks it) on 0.5, anchored with mix 1 to a flat 0.3, is the
    same checkerboard on 0.3; with mix 0.5, on 0.4."""
    size, inner = 48, slice(14, -14)
    checker = torch.from_numpy(((np.indices((size, size)).sum(0) % 2) * 2 - 1).astype(np.float32)) * 0.2
    x = (0.5 + checker).expand(1, 3, size, size)
    flat = torch.full((1, 3, size, size), 0.3)
    for mix, level in ((1.0, 0.3), (0.5, 0.4)):
        got = anchored(x, flat, 3.0, mix)[..., inner, inner]
        np.testing.assert_allclose(got.numpy(), (level + checker[inner, inner]).expand_as(got).numpy(), atol=1e-6)


def test_prior_anchor_removes_a_flicker_the_renders_do_not_have():
    """Frames that are an affine map of their renders plus a per-frame offset summing to 0 over
    the sequence (the renders are one image rolled, so every frame has the same colour sums and
    the offsets do not bias the fit): the anchor with mix 1 gives the mapped renders exactly, with
    mix 0.5 half the offsets; the renders' own motion (the roll) is kept."""
    size, n = 32, 4
    base = ndimage.gaussian_filter(np.random.default_rng(0).random((3, size, size)), (0, 2, 2), mode="wrap")
    renders = torch.from_numpy(np.stack([np.roll(base, 3 * k, axis=2) for k in range(n)]).astype(np.float32))
    mapped = 0.2 + 0.6 * renders.flip(1)  # a channel swap and a contrast change
    offsets = torch.tensor([0.05, -0.03, 0.02, -0.04])[:, None, None, None]
    frames = mapped + offsets
    np.testing.assert_allclose(prior_anchor(frames, renders, 3.0).numpy(), mapped.numpy(), atol=1e-5)
    np.testing.assert_allclose(prior_anchor(frames, renders, 3.0, 0.5).numpy(),
                               (mapped + offsets / 2).numpy(), atol=1e-5)
    with pytest.raises(ValueError, match="mix"):
        prior_anchor(frames, renders, 3.0, 0.0)


# --------------------------------------------------------------------------- the street


def _street(n: int = 5, size: int = 24, step: float = 0.8, offsets=(0.0, 0.06, -0.04, 0.08, -0.02, 0.05, 0.0),
            sky=None):
    """A camera 2 m over the plane z = 0 (world z up), looking level along +x and moving `step` m
    a frame, over a smooth ground texture under a smooth sky (`sky`: unit directions [..., 3] ->
    colours); each frame's colours off by its own constant (a flicker). -> (frames [N, 3, H, W],
    cameras, offsets [N], ground(x, y), sky(dirs))."""
    rot = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # camera x, y, z -> world -y, -z, +x
    cams = []
    for k in range(n):
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = rot, [k * step, 0.0, 2.0]
        cams.append(Camera(intrinsics(70.0, size, size), c2w, size, size))

    def ground(x, y):
        return np.stack([0.4 + 0.1 * np.sin(0.4 * x), 0.3 + 0.1 * np.cos(0.5 * y), 0.35 + 0.05 * np.sin(0.3 * (x + y))], -1)

    def smooth_sky(d):
        return np.stack([0.5 + 0.2 * d[..., 2], 0.6 + 0.1 * d[..., 1], 0.8 - 0.1 * d[..., 2]], -1)

    sky = sky or smooth_sky
    offsets = np.array(offsets[:n])
    frames = []
    for cam, c in zip(cams, offsets):
        o, d = cam.rays(normalize=False)
        t = np.where(d[:, 2] < 0, -o[:, 2] / np.where(d[:, 2] < 0, d[:, 2], -1.0), np.inf)
        p = o + d * np.where(np.isfinite(t), t, 0.0)[:, None]
        unit = d / np.linalg.norm(d, axis=-1, keepdims=True)
        col = np.where(np.isfinite(t)[:, None], ground(p[:, 0], p[:, 1]), sky(unit)) + c
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
    pts, t, street = street_points(cam, depth, 0.0, far=12.0)
    fall = -d[:, 2]
    want_t = np.where(fall > 0, 2.0 / np.where(fall > 0, fall, 1.0), np.inf)
    np.testing.assert_allclose(t, want_t, rtol=1e-12)
    np.testing.assert_array_equal(street, (want_t < 12.0) & (want_t <= depth.ravel() * (1 + DEPTH_TOL)))
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
    out = street_transfer(imgs, cams, depths, 0.0, far=12.0, view_m=view_m).numpy()
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
    half = street_transfer(imgs, cams, depths, 0.0, far=12.0, view_m=view_m, mix=0.5).numpy()
    np.testing.assert_allclose(half, 0.5 * (x + out), atol=1e-5)
    with pytest.raises(ValueError, match="mix"):
        street_transfer(imgs, cams, depths, 0.0, mix=0.0)


def test_street_transfer_leaves_what_the_prior_puts_in_front():
    """Pixels where the prior's surface stands before the plane (a wall, a car) are not street:
    they keep their own colours exactly."""
    imgs, cams, _, _, _ = _street(n=3)
    depths = [np.full((24, 24), np.inf) for _ in cams]
    for dep in depths:
        dep[:, 10:14] = 3.0
    out = street_transfer(imgs, cams, depths, 0.0, far=12.0)
    torch.testing.assert_close(out[..., 10:14], imgs[..., 10:14], rtol=0, atol=0)
    assert not torch.allclose(out[..., 16:, :8], imgs[..., 16:, :8])


def test_prior_ground_is_the_street_under_the_cameras_among_the_gaussians():
    """Gaussians' means of a street at z = 0.1 (sd 0.05 m), a few floaters under it and facades up
    to 20 m; cameras 2 m up: the street's height is the mode of what lies under the cameras
    (within 0.06 of 0.1 with `street_height`'s 0.1 m bins smoothed over 0.5 m), where the lower
    half's mode (a fused cloud's rule) would put it 0.25 m low, under the road; no means under the
    cameras: None."""
    rng = np.random.default_rng(0)
    z = np.concatenate([0.1 + rng.normal(0, 0.05, 4000), rng.uniform(-0.5, 0.1, 300), rng.uniform(0.0, 20.0, 4000)])
    means = np.zeros((len(z), 3))
    means[:, 2] = z
    assert abs(prior_ground(means, [2.0, 2.1]) - 0.1) <= 0.06
    assert prior_ground(means[z > 1.6], [2.0, 2.1]) is None


def _rotation(axis, deg: float) -> np.ndarray:
    """[3, 3] the rotation by `deg` degrees about the unit `axis` (Rodrigues' formula)."""
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    t = np.radians(deg)
    return np.eye(3) + np.sin(t) * k + (1.0 - np.cos(t)) * k @ k


def _lane(seed: int = 0, kerb_sides: int = 2, n: int = 5000) -> tuple[np.ndarray, np.ndarray]:
    """A straight lane: 16 ground cameras at z = 2.1 along x from 0 to 30 m, over the means of a
    Gaussian prior: 80% on the level street z = 0.1 (1 cm noise) within 5 m of the lane, 10% three
    cars (up to 1.5 m above the road, beside the lane), 10% a kerb band at +0.15 along the lane's
    edge (on one side or both), and facades beyond the corridor. -> (means [M, 3], centres [16, 3])."""
    rng = np.random.default_rng(seed)
    centres = np.stack([np.linspace(0.0, 30.0, 16), np.zeros(16), np.full(16, 2.1)], 1)
    nk = nc = n // 10
    nr = n - nk - nc
    road = np.c_[rng.uniform(-5, 35, nr), rng.uniform(-5, 5, nr), 0.1 + rng.normal(0, 0.01, nr)]
    cars = np.concatenate([np.c_[rng.uniform(cx - 2, cx + 2, nc // 3), rng.uniform(1.0, 2.8, nc // 3),
                                 rng.uniform(0.1, 1.6, nc // 3)] for cx in (5.0, 14.0, 26.0)])
    side = rng.choice([-1.0, 1.0], nk) if kerb_sides == 2 else np.ones(nk)
    kerb = np.c_[rng.uniform(-5, 35, nk), side * rng.uniform(3.5, 5.0, nk), np.full(nk, 0.25)]
    facades = np.c_[rng.uniform(-5, 35, 2000), rng.choice([-9.0, 9.0], 2000), rng.uniform(0.1, 12.0, 2000)]
    return np.concatenate([road, cars, kerb, facades]), centres


# NOTE: with the kerb on one side only, the three fits `level_street` makes (one and two refits)
# stop before the trimming has dropped the kerb: 0.77 to 0.81 deg on the level street (height 0.13)
# and 5.62 to 5.66 on the 5 deg one, at seeds 0 to 2; six fits reach 0.02 to 0.06 and 5.02. A
# library bug (reported), held here as a strict xfail so that its fix shows.
_ONE_KERB = pytest.param(1, marks=pytest.mark.xfail(strict=True, reason="level_street stops after 3 fits: a "
                                                    "one-sided kerb with cars leaves it 0.8 deg off"))


@pytest.mark.parametrize("kerb_sides", [2, _ONE_KERB])
def test_level_street_finds_the_plane_under_the_lane_and_its_tilt(kerb_sides):
    """The means of a level street at z = 0.1 under a lane at z = 2.1, with 20% outliers (cars up
    to 1.5 m above the road, a kerb band at +0.15) and facades outside the corridor: tilt under
    0.2 deg, height 0.1, the street on the plane. The same scene turned 5 deg about a horizontal
    axis 30 deg from x (the cameras with it): the plane's tilt is the angle between the turned
    vertical and the vertical, arccos((R e_z)_z) = 5 deg (closed form), found within 0.3 deg.
    Fewer means under the lane than `min_points`: no height."""
    means, centres = _lane(kerb_sides=kerb_sides)
    level = level_street(means, centres)
    assert level["tilt_deg"] < 0.2, level
    assert abs(level["height"] - 0.1) < 0.02 and level["rms_m"] < 0.03, level
    rot = _rotation([np.cos(np.radians(30.0)), np.sin(np.radians(30.0)), 0.0], 5.0)
    want = np.degrees(np.arccos((rot @ [0.0, 0.0, 1.0])[2]))
    assert abs(want - 5.0) < 1e-9
    turned = level_street(means @ rot.T, centres @ rot.T)
    assert abs(turned["tilt_deg"] - want) < 0.3, turned
    few = level_street(means[:40], centres)
    assert few["height"] is None and few["points"] == 40 and few["tilt_deg"] == float("inf")
    assert level_street(means, centres, min_points=len(means) + 1)["height"] is None


def _stand_in_view(means: np.ndarray, cams: list[Camera], monkeypatch, seq_id: str = "lane/seq") -> SequenceView:
    """A `SequenceView` of one sequence whose frames are `cams` (the scene's ground frames too),
    over a stand-in prior whose scene's points (`SceneGeometry.points`) are `means` [M, 3] and whose
    depth is +inf everywhere (nothing in front of the street, the whole upper half sky)."""
    frames = [types.SimpleNamespace(camera=lambda c=c: c, height=c.height, width=c.width) for c in cams]
    scene = types.SimpleNamespace(name=seq_id.split("/")[0], ground=frames)
    prior = types.SimpleNamespace(points=lambda s: np.asarray(means, np.float32) if s is scene else None)
    monkeypatch.setattr(SequenceView, "depths", lambda self, h, w: [np.full((h, w), np.inf) for _ in self.sequence.frames])
    return SequenceView(prior, scene, types.SimpleNamespace(id=seq_id, frames=frames), [])


def _street_means(tilt_deg: float = 0.0) -> np.ndarray:
    """The means of a street's Gaussians on z = 0 under `_street`'s cameras (a 0.25 m grid, 17 m x
    10 m), turned `tilt_deg` about the lane's line (world x)."""
    gx, gy = np.meshgrid(np.arange(-5.0, 12.0, 0.25), np.arange(-5.0, 5.01, 0.25))
    means = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    return means @ _rotation([1.0, 0.0, 0.0], tilt_deg).T


def test_street_from_one_view_transfers_on_a_level_street_and_steps_aside_on_a_tilted_one(monkeypatch):
    """The step on a stand-in prior: under a level street it finds the level (tilt ~0, the street's
    height 0 by `prior_ground`) and its output is `street_transfer`'s at its config; under the same
    street turned 5 deg about the lane it records the tilt and `level` False and returns its input
    as it is (the same tensor)."""
    imgs, cams, _, _, _ = _street()
    cfg = StreetConfig(mix=0.8)
    step = StreetFromOneView(cfg)
    view = _stand_in_view(_street_means(), cams, monkeypatch)
    out = step(imgs, view)
    found = step.levels["lane"]
    assert found["level"] is True and found["tilt_deg"] < 0.01 and found["rms_m"] < 0.01
    assert abs(found["ground"]) <= 0.06
    h, w = imgs.shape[-2:]
    want = street_transfer(imgs, cams, [np.full((h, w), np.inf)] * len(cams), found["ground"], mix=0.8,
                           view_m=cfg.view_m, far=cfg.far_m)
    torch.testing.assert_close(out, want, rtol=0, atol=0)
    assert (out - imgs).abs().max() > 0.02  # the flicker on the street is gone
    tilted = StreetFromOneView(cfg)
    view = _stand_in_view(_street_means(5.0), cams, monkeypatch, "hill/seq")
    assert tilted(imgs, view) is imgs
    found = tilted.levels["hill"]
    assert found["level"] is False and abs(found["tilt_deg"] - 5.0) < 0.05
    # the finding is made once a scene: the next sequence of the scene does not refit it
    monkeypatch.setattr(SequenceView, "means", lambda self: pytest.fail("refitted"))
    assert tilted(imgs, view) is imgs


# --------------------------------------------------------------------------- the sky


def _sky_pixels(cam, depth):
    """[H, W] the pixels `sky_fit` treats as sky: nothing of the prior's, the ray above the horizon."""
    _, d = cam.rays()
    return (np.isinf(depth).ravel() & (d[:, 2] > 0)).reshape(depth.shape)


def test_sky_fit_is_one_function_of_the_direction_for_the_sequence():
    """A sky linear in the ray's direction, each frame off by its own constant (`_street`): with
    no trimming, the interior sky pixels of every frame become that sky plus the offsets' mean
    (the least squares of a degree 1 or 2 polynomial over the same directions in every frame);
    the street keeps its own colours exactly; the mask's border pixels go half the way; half the
    mix is half the way; the residual is the offsets' RMS about their mean."""
    imgs, cams, offsets, _, sky = _street()
    n, _, h, w = imgs.shape
    depths = [np.full((h, w), np.inf) for _ in cams]
    mean = offsets.mean()  # the cameras only translate: every frame's sky pixels see the same directions
    for degree in (1, 2):
        res, rms = sky_fit(imgs, cams, depths, degree=degree, trim=0.0)
        out = res.numpy()
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
        # each pixel's residual is its frame's offset from the mean, in all 3 channels
        assert rms == pytest.approx(np.sqrt(3 * np.mean((offsets - mean) ** 2)), rel=1e-4)
    assert inner.sum() > 50
    half, _ = sky_fit(imgs, cams, depths, mix=0.5, trim=0.0)
    np.testing.assert_allclose(half.numpy(), 0.5 * (imgs.numpy() + sky_fit(imgs, cams, depths, trim=0.0)[0].numpy()),
                               atol=1e-5)
    for bad in (dict(mix=0.0), dict(mix=1.5), dict(degree=-1), dict(trim=1.0)):
        with pytest.raises(ValueError, match="sky_fit"):
            sky_fit(imgs, cams, depths, **bad)
    with pytest.raises(ValueError, match="2 depths"):
        sky_fit(imgs, cams, depths[:2])
    ground = [np.full((h, w), 5.0) for _ in cams]  # the prior everywhere: no sky
    same, rms = sky_fit(imgs, cams, ground)
    assert rms == 0.0 and torch.equal(same, imgs)


def _ghosted(n: int = 4):
    """`_street`'s frames with no flicker (the sky exactly its smooth function of the direction)
    and one frame's dark ghost over a few of its sky pixels. -> (frames, clean frames, cameras)."""
    clean, cams, _, _, _ = _street(n=n, offsets=(0.0,) * n)
    ghosted = clean.clone()
    ghosted[2, :, 3:7, 8:14] = 0.1
    return ghosted, clean, cams


def test_sky_fit_trims_a_ghost():
    """One frame paints a dark ghost over a few of its sky pixels (under a fifth of the
    sequence's): the trimmed fit is the true sky, exactly, in every frame, the ghost painted
    over, and the prior's building kept as it is; the untrimmed one is pulled towards the ghost."""
    ghosted, clean, cams = _ghosted()
    n, _, h, w = ghosted.shape
    depths = [np.full((h, w), np.inf) for _ in range(n)]
    depths[1][2:6, 4:9] = 20.0  # a building of the prior's against the sky: left as it is
    m = _sky_pixels(cams[0], depths[0])
    inner = m & (ndimage.uniform_filter(m.astype(float), 3, mode="nearest") > 0.999)
    assert 0 < 24 < 0.2 * n * m.sum()
    out, rms = sky_fit(ghosted, cams, depths)
    out = out.numpy()
    assert rms < 1e-6
    for k in range(n):
        keep = ~_sky_pixels(cams[k], depths[k])
        np.testing.assert_array_equal(out[k][:, keep], ghosted[k].numpy()[:, keep])
        ok = inner & ~ndimage.binary_dilation(keep, iterations=1)
        np.testing.assert_allclose(out[k][:, ok], clean[k].numpy()[:, ok], atol=1e-5)
    pulled, pulled_rms = sky_fit(ghosted, cams, depths, trim=0.0)
    assert np.abs(pulled.numpy()[0][:, inner] - clean[0].numpy()[:, inner]).max() > 0.01 and pulled_rms > 0.01


def test_sky_from_one_fit_applies_on_a_smooth_sky_and_steps_aside_on_a_textured_one(monkeypatch):
    """The step on a stand-in view: a sky that is a gradient of the direction (linear in it, the
    closed form `_street` paints) with a ghost in one frame is fitted with a residual of ~0 and
    every frame's interior sky becomes the gradient (the ghost painted over); a checkerboard of
    +-0.3 in every channel over that sky is no smooth function of the direction (the smooth sky
    leaves 0.3 sqrt(3) on every pixel, the fit not much less: far over `max_rms`): the step
    records it and returns its input as it is."""
    ghosted, clean, cams = _ghosted()
    n, _, h, w = ghosted.shape
    step = SkyFromOneFit(SkyConfig(mix=1.0))
    view = _stand_in_view(_street_means(), cams, monkeypatch, "lane/smooth")
    out = step(ghosted, view)
    assert step.residuals["lane/smooth"] < 1e-6
    m = _sky_pixels(cams[0], np.full((h, w), np.inf))
    inner = m & (ndimage.uniform_filter(m.astype(float), 3, mode="nearest") > 0.999)
    torch.testing.assert_close(out[:, :, inner], clean[:, :, inner], rtol=0, atol=1e-5)
    torch.testing.assert_close(out[:, :, ~m], ghosted[:, :, ~m], rtol=0, atol=0)
    assert (ghosted[2, :, inner] - clean[2, :, inner]).abs().max() > 0.3  # the ghost was there
    dim = clean * 0.6 + 0.1  # the smooth sky scaled into [0.4, 0.6]: room for +-0.3 in [0, 1]
    checker = torch.from_numpy(((np.indices((h, w)).sum(0) % 2) * 2 - 1) * 0.3).float()
    textured = torch.where(torch.from_numpy(m), dim + checker, dim)
    assert 0.0 <= float(textured.min()) and float(textured.max()) <= 1.0
    step = SkyFromOneFit(SkyConfig(mix=1.0))
    view = _stand_in_view(_street_means(), cams, monkeypatch, "lane/cloudy")
    assert step(textured, view) is textured
    # least squares over the kept pixels does no worse than the smooth sky, 0.3 sqrt(3) on every pixel
    assert 0.3 < step.residuals["lane/cloudy"] <= 0.3 * np.sqrt(3) + 1e-9
    assert step.residuals["lane/cloudy"] > 5 * step.cfg.max_rms


# --------------------------------------------------------------------------- the prior's depth


def test_prior_depth_of_an_opaque_plane():
    """A wall of small opaque Gaussians 6 m ahead: planar depth 6 where it covers the pixel, +inf
    (a direction) where nothing does, at the asked size with the intrinsics scaled to it."""
    xs, ys = np.meshgrid(np.linspace(-3, 3, 61), np.linspace(-3, 0, 31))
    xyz = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 6.0)], -1)  # the upper half of the view
    model = GaussianModel.from_points(xyz, np.full_like(xyz, 0.5), 0, opacity=0.99)
    scene = object()

    class Prior(GaussianGeometry):
        config = types.SimpleNamespace(sh_degree=0, render_near_m=0.1)

        def scene_model(self, s):
            return (model,) if s is scene else None

    prior = Prior()
    frame = types.SimpleNamespace(camera=lambda: _cam(size=32, fov=40.0))
    depth = prior_depth(prior, scene, frame, 16, 12)
    assert depth.shape == (12, 16)
    np.testing.assert_allclose(depth[1:5, 3:13], 6.0, rtol=1e-3)  # the wall (y < 0 is up)
    assert np.isinf(depth[8:]).all()  # below it: nothing


# --------------------------------------------------------------------------- in the pipeline


def _geo_config(anchor: float = 0.0, street: float = 0.0, sky: float = 0.0, **fields) -> AdditionsConfig:
    """`skyeyes-geo`'s smoke config at 16 x 16 on one thread, with the steps after sampling at these
    mixes and no carried noise."""
    from reference.methods.skyeyes_geo import PRESETS

    base = PRESETS["smoke"]
    return dataclasses.replace(base, core=dataclasses.replace(base.core, resolution=16), threads=1, device="cpu",
                               noise=CarriedNoiseConfig(), anchor=PriorAnchorConfig(mix=anchor),
                               street=StreetConfig(mix=street), sky=SkyConfig(mix=sky), **fields)


@pytest.mark.parametrize("anchor, street, sky", [(0.5, 0.8, 1.0), (0.5, 0.0, 1.0), (0.0, 0.8, 0.0), (0.0, 0.0, 0.7),
                                                 (0.6, 0.0, 0.0), (0.0, 0.0, 0.0)])
def test_pipeline_takes_the_anchor_then_the_street_then_the_sky(tmp_path, monkeypatch, anchor, street, sky):
    """`render_sequence` after decoding: the prior anchor, the street, the sky, each on the one
    before's frames and on one `SequenceView` of the sequence (the prior, its renders), each left
    out at mix 0; with none, no view at all."""
    from reference.common.diffusion import core
    from reference.common.priors import frame_key
    from reference.methods.skyeyes_geo import SkyeyesGeo

    prior = object()
    m = SkyeyesGeo(_geo_config(anchor, street, sky), tmp_path, prior_method=prior, progress=False)
    m._figure_written = True  # no figure: nothing here is a model's sample
    calls = []

    def recorder(name, f):
        def call(self, imgs, view):
            calls.append((name, imgs.clone(), view))
            return f(imgs)
        return call

    monkeypatch.setattr(PriorAnchor, "__call__", recorder("anchor", lambda x: x + 0.1))
    monkeypatch.setattr(StreetFromOneView, "__call__", recorder("street", lambda x: x * 0.5))
    monkeypatch.setattr(SkyFromOneFit, "__call__", recorder("sky", lambda x: x + 0.2))
    views = []
    monkeypatch.setattr(SkyeyesGeo, "_generate", lambda self, cc, seed, view: views.append(view) or
                        torch.zeros(len(cc), 3, 16, 16))
    monkeypatch.setattr(core, "decode", lambda x, cfg, device=None: torch.full((len(x), 3, 16, 16), 0.3))
    scene = types.SimpleNamespace(name="s")
    frames = [types.SimpleNamespace(file=f"{k}.png", height=16, width=16) for k in range(3)]
    seq = types.SimpleNamespace(id="s/q", frames=frames)
    priors = [np.full((16, 16, 3), 0.1 * k, np.float32) for k in range(3)]
    m._scene_models["s"] = {frame_key(scene, f): p for f, p in zip(frames, priors)}
    out = np.stack(list(m.render_sequence(scene, seq)))
    want = [name for name, mix in (("anchor", anchor), ("street", street), ("sky", sky)) if mix]
    assert [c[0] for c in calls] == want
    x = 0.3
    for name, imgs, view in calls:
        np.testing.assert_allclose(imgs.numpy(), x, atol=1e-6)  # the frames the step before left
        assert view is views[0] and isinstance(view, SequenceView)
        assert view.prior is prior and view.sequence is seq and view.priors == priors
        x = {"anchor": x + 0.1, "street": x * 0.5, "sky": x + 0.2}[name]
    assert views == [calls[0][2] if calls else None]
    np.testing.assert_allclose(out, x, atol=1e-6)


@pytest.mark.parametrize("adds, match", [
    (dict(noise=CarriedNoiseConfig(share=0.5), condition="aerial"), "carried noise"),
    (dict(anchor=PriorAnchorConfig(mix=0.5), condition="aerial"), "prior anchor"),
    (dict(street=StreetConfig(mix=0.5), prior_method="mvs"), "street from one view"),
    (dict(sky=SkyConfig(mix=0.5), prior_method="mvs"), "sky from one fit"),
])
def test_adapted_refuses_additions_without_what_they_read(adds, match):
    """`adapted`: every addition needs the prior's renders as the condition (not the nearest aerial
    view), the street and the sky a Gaussian prior (its depth and Gaussians): refused naming the
    component; the same components on their condition and prior are taken, as is the anchor on a
    prior of another kind."""
    from reference.common.diffusion.pipeline import adapted

    base = AdditionsConfig()
    with pytest.raises(ValueError, match=match):
        adapted(dataclasses.replace(base, **adds), "controlnet")
    fine = {k: v for k, v in adds.items() if k not in ("condition", "prior_method")}
    adapted(dataclasses.replace(base, **fine), "controlnet")
    adapted(dataclasses.replace(base, **fine, prior_method="gaussians3d"), "controlnet")
    adapted(dataclasses.replace(base, anchor=PriorAnchorConfig(mix=0.5), noise=CarriedNoiseConfig(share=1.0),
                                prior_method="mvs"), "controlnet")
    adapted(dataclasses.replace(DiffusionConfig(), condition="aerial"), "controlnet")  # the paper's: nothing to refuse
