"""The per-frame generative baselines `ip2p` (InstructPix2Pix) and `gvg` (Geospecific View
Generation): registry and presets, IP2P's training dropout, gvg's condition channels on a scene
with a known answer, and both end to end through the method API on a tiny hand-made dataset.

The priors here are STAND-INS (test only): ip2p needs none (its condition is the nearest aerial
view); gvg's is the ground truth blurred, with a known depth and coverage
(`builders.skyeyes.StandInGeometryPrior`). The real gvg renders the `mvs` method's fused cloud.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

import diffusers  # noqa: F401  (a hard dependency of reference: a broken install fails here, never skips)

from builders.skyeyes import SIZE, StandInGeometryPrior, StandInPrior, make_tiny_dataset  # noqa: E402
from reference.common.diffusion import guidance  # noqa: E402
from reference.common.diffusion.config import frame_by_frame  # noqa: E402
from reference.methods import METHODS, get_method_class  # noqa: E402
from reference.methods import gvg as gvg_mod  # noqa: E402
from reference.methods import ip2p as ip2p_mod  # noqa: E402
from reference.methods.skyeyes import PRESETS as SKYEYES  # noqa: E402
from skyeyes_bench.data.layout import open_dataset  # noqa: E402

#: Skyeyes' smoke preset (the CPU formulation: concat, residual, EMA, min-SNR) on a tiny UNet.
TINY = dataclasses.replace(
    SKYEYES["smoke"],
    core=dataclasses.replace(SKYEYES["smoke"].core, resolution=SIZE, channels=(16, 32), attention=(False, True),
                             head_dim=8, embed_dim=16, norm_groups=4),
    acm_steps=2, acm_batch=2, sample_steps=2, ckpt_every=1, figure_frames=3, device="cpu",
    threads=1)  # one thread: a second one spins on a shared 2-core machine (conftest.one_torch_thread)

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest: tiny tensors, one thread


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return make_tiny_dataset(tmp_path_factory.mktemp("tiny") / "ds", frames=4)


# --------------------------------------------------------------------------- registry, presets


def test_registry_and_presets_follow_skyeyes(monkeypatch):
    assert METHODS["ip2p"] == "reference.methods.ip2p:InstructPix2Pix"
    assert METHODS["gvg"] == "reference.methods.gvg:GVG"
    ip2p, gvg = get_method_class("ip2p"), get_method_class("gvg")
    assert (ip2p.name, gvg.name) == ("ip2p", "gvg")
    assert set(ip2p.presets) == set(gvg.presets) == {"smoke", "small", "paper"}
    for k, sk in SKYEYES.items():
        p = ip2p.presets[k]
        assert p.core == dataclasses.replace(sk.core, conditioning="concat", null_prompt=True,
                                             prompt_text=ip2p_mod.INSTRUCTION)
        budget = (sk.acm_steps, sk.acm_anneal, sk.acm_batch, sk.acm_lr, sk.train_crop, sk.mixed_precision)
        assert (p.condition, p.vcm, p.sample_steps) == ("aerial", False, sk.sample_steps)
        assert (p.drop_image, p.drop_text, p.drop_both, p.image_guidance, p.text_guidance) == (0.05, 0.05, 0.05, 1.5, 7.5)
        g = gvg.presets[k]
        assert g.core == dataclasses.replace(sk.core, conditioning="concat", cond_extra=2)
        assert (g.condition, g.vcm, g.prior_method) == ("prior", False, "mvs")
        c = get_method_class("controlnet").presets[k]
        assert (c.condition, c.vcm) == ("aerial", False)
        assert dataclasses.replace(c, condition=sk.condition) == frame_by_frame(sk)  # Skyeyes without its VCM
        for b in (p, g, c):  # one training budget for the diffusion family (issue 36)
            assert (b.acm_steps, b.acm_anneal, b.acm_batch, b.acm_lr, b.train_crop, b.mixed_precision) == budget
    assert [gvg.presets[k].prior_preset for k in ("smoke", "small", "paper")] == ["smoke", "fast", "paper"]
    assert SKYEYES["small"].core.conditioning == "concat"  # the CPU presets already concatenate
    # --device is a config field of both (torch reports two GPUs here; configure checks it exists)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    cfg, applied = ip2p.configure("smoke", device="cuda:1")
    assert cfg.device == "cuda:1" and "device=cuda:1" in applied
    assert gvg.configure("small", device="cpu")[0].device == "cpu"


def test_ip2p_diffuses_frames_and_refuses_what_guidance_cannot_use(tmp_path):
    m = ip2p_mod.InstructPix2Pix(ip2p_mod.ip2p_config(TINY), tmp_path / "a")
    assert not m.config.core.residual  # the aerial view is no estimate of the frame
    assert TINY.core.residual  # (while Skyeyes' formulation diffuses the residual)
    with pytest.raises(ValueError, match="null_prompt"):
        cfg = ip2p_mod.ip2p_config(TINY)
        ip2p_mod.InstructPix2Pix(dataclasses.replace(cfg, core=dataclasses.replace(cfg.core, null_prompt=False)),
                                 tmp_path / "b")
    with pytest.raises(ValueError, match="summing to <= 1"):
        ip2p_mod.InstructPix2Pix(dataclasses.replace(ip2p_mod.ip2p_config(TINY), drop_both=0.95), tmp_path / "c")


def test_ip2p_training_drops_exactly_to_the_null_conditions(tmp_path):
    from reference.common.diffusion import core

    m = ip2p_mod.InstructPix2Pix(ip2p_mod.ip2p_config(TINY), tmp_path / "a")
    cfg = m.config.core
    k = core.encode_cond(torch.rand(400, 3, 4, 4) * 0.5 + 0.25, cfg)
    out, text = m.guidance.drop(k, torch.Generator().manual_seed(5))
    di, dt = guidance.draw_drops(400, torch.Generator().manual_seed(5), 0.05, 0.05, 0.05)  # the same draws
    assert di.any() and dt.any() and (di & dt).any()
    assert torch.equal(text, ~dt)
    assert torch.equal(out[di], torch.zeros_like(out[di]))  # no coordinate channels at smoke
    assert torch.equal(out[~di], k[~di])


# --------------------------------------------------------------------------- gvg's condition


def test_gvg_condition_of_a_plane_at_known_depth(one_torch_thread):
    """A textured plane facing the camera at x = 8 m, covering y in [0, 10] m: inverse depth
    2 / 8 and mask 1 wherever a ray meets it well inside, mask 0, inverse depth 0 and the
    background's colour where no ray can meet it."""
    from reference.common.geometry.cloud import PointCloud
    from skyeyes_bench.cameras import Camera

    cam = Camera.from_ypr([0.0, 0.0, 2.0], 0.0, 0.0, fov_deg=90, width=32, height=32)  # looks along +x
    d, step = 8.0, 0.25
    ys, zs = np.meshgrid(np.arange(0.0, 10.0 + 1e-9, step), np.arange(-6.0, 10.0 + 1e-9, step))
    n = ys.size
    xyz = np.stack([np.full(n, d), ys.ravel(), zs.ravel()], 1).astype(np.float32)
    rgb = np.tile(np.array([[0.8, 0.3, 0.1]], np.float32), (n, 1))
    cloud = PointCloud(xyz, rgb, np.tile(np.array([[-1.0, 0, 0]], np.float32), (n, 1)), np.full(n, 2 * step, np.float32))
    from reference.common.geometry import splat
    from reference.methods.mvs import geometry_render

    background = np.full((32, 32, 3), 0.2, np.float32)
    raw = geometry_render(splat.surfels(cloud), cam, background, opacity=0.98, near=0.5)
    cond = gvg_mod.condition_channels(raw, depth_ref_m=2.0)
    assert cond.shape == (32, 32, 5) and cond.dtype == np.float32
    # Closed form: each pixel's ray meets the plane x = 8 at o + dir * 8 (camera z = 1: planar depth 8).
    o, dirs = cam.rays(normalize=False)
    hit = (o + dirs * d).reshape(32, 32, 3)
    inside = (hit[..., 1] > 1.0) & (hit[..., 1] < 9.0) & (hit[..., 2] > -5.0) & (hit[..., 2] < 9.0)
    outside = hit[..., 1] < -1.0  # more than 4 disc radii from the plane's edge at y = 0
    assert inside.sum() > 150 and outside.sum() > 150
    np.testing.assert_allclose(raw[inside][:, 3], d, rtol=1e-5)  # planar depth, metres
    np.testing.assert_allclose(cond[inside][:, 3], 2.0 / d, rtol=1e-5)
    assert (cond[inside][:, 4] == 1).all()
    np.testing.assert_allclose(cond[inside][:, :3], np.broadcast_to(rgb[0], (inside.sum(), 3)), atol=0.03)
    assert (cond[outside][:, 3] == 0).all() and (cond[outside][:, 4] == 0).all()
    np.testing.assert_allclose(cond[outside][:, :3], 0.2, atol=1e-6)
    # nearer than the reference depth: clipped to 1
    near = gvg_mod.condition_channels(np.concatenate([raw[..., :3], raw[..., 3:4] / 8, raw[..., 4:]], -1), 2.0)
    assert (near[inside][:, 3] == 1).all()


# --------------------------------------------------------------------------- end to end


def _run(cls, cfg, tiny, workdir, seed=0, prior=None):
    ds = open_dataset(tiny)
    m = cls(cfg, workdir, seed=seed, prior_method=prior, progress=False)
    m.fit_train(ds)
    out = {}
    for scene in ds.split("test"):
        m.fit_scene(scene)
        for seq in scene.sequences.values():
            out[seq.id] = np.stack(list(m.render_sequence(scene, seq)))
    return m, out


def _render_again(m, tiny, seed):
    """Every test frame sampled again by the fitted `m` with another sampling seed."""
    m.seed = seed
    ds = open_dataset(tiny)
    return {seq.id: np.stack(list(m.render_sequence(ds.scenes[seq.scene], seq)))
            for seq in ds.sequences("test")}


def _check_frames(out, tiny):
    ds = open_dataset(tiny)
    for seq in ds.sequences("test"):
        frames = out[seq.id]
        assert frames.shape == (len(seq), SIZE, SIZE, 3) and frames.dtype == np.float32
        assert np.isfinite(frames).all() and frames.min() >= 0 and frames.max() <= 1


def test_ip2p_end_to_end_deterministic_in_the_seed(tiny, tmp_path):
    cfg = ip2p_mod.ip2p_config(TINY)
    prior = StandInPrior(tmp_path / "prior")
    m, a = _run(ip2p_mod.InstructPix2Pix, cfg, tiny, tmp_path / "a", prior=prior)
    _check_frames(a, tiny)
    assert prior.fitted == []  # its condition is the nearest aerial view
    assert m.acm.null_prompt is not None and m.acm.controlnet is None
    assert m.acm.unet.conv_in.in_channels == 6  # noisy frame + aerial view
    assert set(m.training) == {"acm"} and (tmp_path / "a" / "figure.png").is_file()
    guided = m.guidance.sampling_model(m.acm)
    assert isinstance(guided, guidance.GuidedModel) and (guided.s_image, guided.s_text) == (1.5, 7.5)
    _, b = _run(ip2p_mod.InstructPix2Pix, cfg, tiny, tmp_path / "b")  # the stage from the cache
    c = _render_again(m, tiny, seed=1)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
        assert np.abs(a[k] - c[k]).max() > 1e-3


def test_gvg_end_to_end_deterministic_in_the_seed(tiny, tmp_path):
    cfg = gvg_mod.gvg_config(TINY, "smoke")
    prior = StandInGeometryPrior(tmp_path / "prior")
    m, a = _run(gvg_mod.GVG, cfg, tiny, tmp_path / "a", prior=prior)
    _check_frames(a, tiny)
    assert prior.fitted == ["train-0-lane00", "test-0-lane00"]  # the geometry of train and test lanes
    assert m.config.core.residual  # the projected texture is an estimate of the frame
    assert m.acm.unet.conv_in.in_channels == 3 + 5  # noisy frame + colour, depth, mask
    # its conditions: the stand-in's colour, inverse depth 2 / 4 and the mask, top quarter unseen
    c = next(iter(m.scene_model(open_dataset(tiny).split("test")[0]).values()))  # its fit: {frame key: condition}
    assert c.shape == (SIZE, SIZE, 5)
    assert (c[SIZE // 4:, :, 3] == 0.5).all() and (c[SIZE // 4:, :, 4] == 1).all()
    assert (c[: SIZE // 4, :, 3:] == 0).all()
    _, b = _run(gvg_mod.GVG, cfg, tiny, tmp_path / "b", prior=StandInGeometryPrior(tmp_path / "prior"))
    d = _render_again(m, tiny, seed=1)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
        assert np.abs(a[k] - d[k]).max() > 1e-3
    with pytest.raises(ValueError, match=r"fused MVS cloud's \('mvs'\)"):
        gvg_mod.GVG(dataclasses.replace(cfg, prior_method="sugar"), tmp_path / "x")


def test_gvg_prior_is_the_mvs_geometry_of_its_stereo_preset(tmp_path):
    m = gvg_mod.GVG(gvg_mod.PRESETS["small"], tmp_path / "a")
    prior = m.prior
    from reference.common.mvs_cloud import MVSCloud
    from reference.methods.mvs import MVS
    from reference.methods.mvs import PRESETS as MVS_PRESETS

    # the shared part, not the `mvs` row (no method instantiates another)
    assert type(prior) is MVSCloud and not isinstance(prior, MVS)
    assert prior.geometry and prior.name == "mvs-geometry"

    assert prior.config == dataclasses.replace(MVS_PRESETS["fast"], train_lanes=0, device="cpu")


def test_baselines_follow_skyeyes_budget_when_it_changes(monkeypatch):
    """The baselines train with Skyeyes' budget at every preset: a change to Skyeyes' steps or
    rate decay reaches them, and only the VCM is taken off."""
    from reference.common.diffusion import config, presets

    annealed = {k: dataclasses.replace(v, acm_steps=v.acm_steps + 2000, acm_anneal=2000, mixed_precision="no")
                for k, v in presets.PRESETS.items()}
    monkeypatch.setattr(presets, "PRESETS", annealed)
    got = presets.baseline_presets(lambda k, v: v)
    for k in annealed:
        assert got[k] == config.frame_by_frame(annealed[k])
        assert (got[k].acm_steps, got[k].acm_anneal, got[k].mixed_precision) == (annealed[k].acm_steps, 2000, "no")
        assert got[k].vcm is False