"""Skyeyes / SkyeyesNoVCM / ControlNetBaseline (and SkyeyesGeoNoVCM's prior anchor) end to end on a
tiny hand-made dataset.

The prior here is a STAND-IN (test only): the ground-truth frame blurred and noised. The real
method uses the SuGaR prior, fitted on aerial views only.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import diffusers  # noqa: F401  (a hard dependency of reference: a broken install fails here, never skips)

from builders.skyeyes import SIZE, StandInPrior, make_tiny_dataset  # noqa: E402
from reference.methods.controlnet import ControlNetBaseline  # noqa: E402
from reference.common.priors import nearest_aerial, render_priors  # noqa: E402
from reference.methods.skyeyes import PRESETS, Skyeyes, SkyeyesNoVCM  # noqa: E402
from reference.common.diffusion.core import CoreConfig  # noqa: E402
from reference.common.diffusion.stages import stage_ckpt  # noqa: E402
from skyeyes_bench.data.layout import open_dataset  # noqa: E402
from skyeyes_bench.paths import cache_dir  # noqa: E402


TINY = dataclasses.replace(
    PRESETS["smoke"],
    core=CoreConfig(resolution=SIZE, channels=(16, 32), attention=(False, True), head_dim=8, embed_dim=16,
                    norm_groups=4),
    base_steps=4, base_batch=4, acm_steps=4, acm_batch=4, vcm_steps=2, vcm_batch=1, clip_frames=4,
    sample_steps=4, ckpt_every=2, figure_frames=3)


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest: tiny tensors, one thread


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return make_tiny_dataset(tmp_path_factory.mktemp("tiny") / "ds")


def _run(cls, tiny, workdir, config=TINY, **kw):
    ds = open_dataset(tiny)
    cfg = dataclasses.replace(config, **kw) if kw else config
    if cls is not Skyeyes:
        cfg = dataclasses.replace(cfg, vcm=False, condition="aerial" if cls is ControlNetBaseline else "prior")
    prior = StandInPrior(workdir / "prior")
    m = cls(cfg, workdir, seed=0, prior_method=prior, progress=False)
    m.fit_train(ds)
    out = {}
    for scene in ds.split("test"):
        m.fit_scene(scene)
        for seq in scene.sequences.values():
            out[seq.id] = np.stack(list(m.render_sequence(scene, seq)))
    return m, prior, out


@pytest.mark.parametrize("cls", [Skyeyes, SkyeyesNoVCM, ControlNetBaseline])
def test_methods_render_every_frame(cls, tiny, tmp_path):
    m, prior, out = _run(cls, tiny, tmp_path / "run")
    ds = open_dataset(tiny)
    for seq in ds.sequences("test"):
        frames = out[seq.id]
        assert frames.shape == (len(seq), SIZE, SIZE, 3) and frames.dtype == np.float32
        assert np.isfinite(frames).all() and frames.min() >= 0 and frames.max() <= 1
    assert (tmp_path / "run" / "figure.png").is_file()
    assert (tmp_path / "run" / "config.json").is_file()
    # the prior is fitted on train and test lanes (aerial views), the ControlNet needs none
    assert prior.fitted == ([] if cls is ControlNetBaseline else ["train-0-lane00", "test-0-lane00"])


def test_same_seed_same_frames_and_cached_stages(tiny, tmp_path):
    _, _, a = _run(Skyeyes, tiny, tmp_path / "a")
    _, prior, b = _run(Skyeyes, tiny, tmp_path / "b")  # stages and priors now come from the cache
    assert prior.fitted == []
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


def test_nearest_aerial_is_nearest(tiny):
    ds = open_dataset(tiny)
    scene = ds.scenes["test-0-lane00"]
    for f in scene.ground:
        d = [np.linalg.norm(a.c2w[:3, 3] - f.c2w[:3, 3]) for a in scene.aerial]
        assert nearest_aerial(scene, f) is scene.aerial[int(np.argmin(d))]


def test_render_priors_keys_and_cache(tiny, tmp_path):
    ds = open_dataset(tiny)
    prior = StandInPrior(tmp_path)
    p1, cached1 = render_priors(ds, ds.split("train"), prior, progress=False)
    p2, cached2 = render_priors(ds, ds.split("train"), prior, progress=False)
    assert cached1 == 0 and cached2 > 0  # the second call takes the first's renders, at their cost
    assert prior.fitted == ["train-0-lane00"]
    assert set(p1) == {f"train-0-lane00/{f.file}" for f in ds.scenes["train-0-lane00"].ground}
    for k in p1:
        assert p1[k].shape == (SIZE, SIZE, 3)
        np.testing.assert_array_equal(p1[k], p2[k])


def test_prior_cache_key_holds_the_prior_code(tiny, tmp_path, monkeypatch):
    """Renders cached by other prior code (an older `sugar`, `mvs`) are not reused; the diffusion
    package is not part of that code."""
    import reference.method as M
    from reference.methods.sugar import SuGaR

    ds = open_dataset(tiny)
    prior = StandInPrior(tmp_path)
    render_priors(ds, ds.split("train"), prior, progress=False)
    render_priors(ds, ds.split("train"), prior, progress=False)
    assert prior.fitted == ["train-0-lane00"]
    real = M.code_sha
    monkeypatch.setattr(M, "code_sha", lambda cls, skip=(): "changed" + real(cls, skip))
    render_priors(ds, ds.split("train"), prior, progress=False)
    assert prior.fitted == ["train-0-lane00"] * 2
    assert real(SuGaR, skip=("diffusion",)) != real(SuGaR) and real(SuGaR, skip=("nothing",)) == real(SuGaR)


def test_longer_stage_starts_from_shorter_finished_run(tmp_path):
    import torch

    from reference.common.diffusion import core, train

    key = {"x": 1}
    short = stage_ckpt("acm", key, 2)
    assert not short.exists()
    data = torch.rand(4, 3, SIZE, SIZE, generator=torch.Generator().manual_seed(0)) * 2 - 1
    sched = core.train_scheduler(TINY.core)

    def fit(ckpt, steps):
        mm = core.build_model(TINY.core, control=False, seed=0)
        loss = lambda net, g, part: train.denoise_loss(net, sched, data[torch.randint(0, 4, (2,), generator=g)], None, g)  # noqa: E731
        train.train_loop(mm, core.trainable(mm), loss, steps=steps, lr=1e-3, seed=0, ckpt=ckpt, progress=False)
        return mm.state_dict()

    fit(short, 2)
    long_ckpt = stage_ckpt("acm", key, 4)  # starts as a copy of the finished 2-step run
    assert train.load_checkpoint(long_ckpt)["step"] == 2
    a = fit(long_ckpt, 4)
    b = fit(tmp_path / "fresh.pt", 4)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert stage_ckpt("acm", {"x": 2}, 4).parent != long_ckpt.parent  # other inputs, other folder

    # An interrupted longer run (8 asked, killed after step 6) serves any request of >= 6 steps;
    # a request for fewer steps falls back to the furthest run that did not pass it.
    mm = core.build_model(TINY.core, control=False, seed=0)
    loss = lambda net, g, part: train.denoise_loss(net, sched, data[torch.randint(0, 4, (2,), generator=g)], None, g)  # noqa: E731
    train.train_loop(mm, core.trainable(mm), loss, steps=8, lr=1e-3, seed=0, ckpt=stage_ckpt("acm", key, 8),
                     ckpt_every=2, stop_after=2, progress=False)  # resumed from step 4, killed at 6
    assert train.load_checkpoint(stage_ckpt("acm", key, 8))["step"] == 6
    assert train.load_checkpoint(stage_ckpt("acm", key, 7))["step"] == 6
    assert train.load_checkpoint(stage_ckpt("acm", key, 5))["step"] == 4
    assert train.load_checkpoint(stage_ckpt("acm", key, 3))["step"] == 2


def _cached_prior_seconds() -> float:
    """The seconds every prior render in the cache records it cost (fit + render)."""
    total = 0.0
    for f in (cache_dir() / "reference" / "priors").glob("*.npz"):
        with np.load(f) as z:
            total += float(z["_seconds"])
    return total


def test_cached_stages_and_priors_report_their_original_seconds(tiny, tmp_path):
    """Issue 13: a run whose stages and priors come from the cache reports what producing them
    cost (training.json's seconds), not the ~0 s of loading them."""
    m1, _, _ = _run(Skyeyes, tiny, tmp_path / "a")
    assert m1.cached_s == 0.0  # everything computed
    spent = sum(s["seconds"] for s in m1.training.values())
    m2, prior, _ = _run(Skyeyes, tiny, tmp_path / "b")
    assert prior.fitted == []  # priors from the cache too
    # the checkpoint is written at the last step, a little before the stage's clock stops
    assert all(s["cached_seconds"] == pytest.approx(m1.training[k]["seconds"], rel=0.1, abs=0.2)
               for k, s in m2.training.items())
    stages = sum(s["cached_seconds"] for s in m2.training.values())
    assert stages > 0.5 * spent
    # plus the priors' recorded fit + render seconds (stage seconds are rounded to 0.01 s)
    priors = _cached_prior_seconds()
    assert priors > 0
    assert m2.cached_s == pytest.approx(stages + priors, abs=0.01 * len(m2.training))


def test_annealed_acm_shares_the_constant_steps_and_reports_their_seconds_once(tiny, tmp_path):
    """`acm_anneal`: the constant-rate steps are the plain ACM stage (cached for runs of any
    length), the decay phase its own stage started from it; cached seconds are not counted twice."""
    import torch

    from reference.common.diffusion import train

    m0, _, _ = _run(SkyeyesNoVCM, tiny, tmp_path / "c", acm_steps=4)  # a constant 4-step run
    const = Path(m0.training["acm"]["checkpoint"])
    m1, prior, a = _run(SkyeyesNoVCM, tiny, tmp_path / "a", acm_steps=6, acm_anneal=2)
    assert prior.fitted == []
    priors = _cached_prior_seconds()
    acm = m1.training["acm"]
    assert acm["steps"] == 6 and acm["anneal_steps"] == 2
    assert Path(acm["checkpoint"]).parent.name.startswith("acm-anneal-")
    assert sorted(p.name for p in const.parent.glob("train-*.pt")) == ["train-4.pt"]  # untouched
    # (a checkpoint's clock stops at its last save, a little before the stage's)
    assert acm["cached_seconds"] == pytest.approx(m0.training["acm"]["seconds"], rel=0.2, abs=0.03)
    assert acm["cached_seconds"] > 0.05
    # the constant steps counted once (twice would add acm["cached_seconds"] again); TINY has a
    # base stage too, from the cache
    assert m1.cached_s == pytest.approx(priors + sum(s["cached_seconds"] for s in m1.training.values()), abs=0.03)
    m2, _, b = _run(SkyeyesNoVCM, tiny, tmp_path / "b", acm_steps=6, acm_anneal=2)  # all cached now
    assert m2.cached_s == pytest.approx(priors + m1.training["base"]["seconds"] + acm["seconds"], rel=0.2, abs=0.03)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    m3, _, _ = _run(SkyeyesNoVCM, tiny, tmp_path / "d", acm_steps=6)  # constant: other weights
    w3, w1 = m3.acm.state_dict(), m1.acm.state_dict()
    assert any(not torch.equal(w3[k], w1[k]) for k in w1)
    assert train.load_checkpoint(Path(m3.training["acm"]["checkpoint"]))["step"] == 6
    # a decay whose constant steps are not cached either: everything trained now, nothing cached
    # but the priors and the base stage (exactly; a clock's few ms made it negative once)
    m4, _, _ = _run(SkyeyesNoVCM, tiny, tmp_path / "f", acm_steps=7, acm_anneal=2, acm_batch=3)  # new key
    assert m4.training["acm"]["cached_seconds"] > 0  # the constant steps, trained by this run
    base = float(train.load_checkpoint(Path(m4.training["base"]["checkpoint"]))["seconds"])  # unrounded
    assert m4.cached_s == pytest.approx(priors + base, rel=0, abs=1e-9)
    for bad in (3, 2, -1):  # longer than the run, the whole run, negative: refused before any fit
        with pytest.raises(ValueError, match="acm_anneal"):
            Skyeyes(dataclasses.replace(TINY, acm_steps=2, acm_anneal=bad), tmp_path / "e")


def test_cpu_formulation_end_to_end(tiny, tmp_path):
    """The CPU presets' formulation (issue 13): concat conditioning, residual diffusion, training
    crops, an SDEdit start, EMA and min-SNR weights, through fit and render (VCM included)."""
    core_cfg = dataclasses.replace(TINY.core, conditioning="concat", residual=True, residual_scale=2.0)
    m, _, out = _run(Skyeyes, tiny, tmp_path / "run", core=core_cfg, train_crop=8, sample_strength=0.5,
                     ema_decay=0.9, snr_gamma=5.0)
    assert set(m.training) == {"acm", "vcm"}  # no base stage: the concat UNet is trained whole
    assert m.acm.controlnet is None and m.acm.unet.conv_in.in_channels == 6
    for seq_frames in out.values():
        assert np.isfinite(seq_frames).all() and seq_frames.min() >= 0 and seq_frames.max() <= 1
    with pytest.raises(ValueError, match="needs core.residual"):
        Skyeyes(dataclasses.replace(TINY, sample_strength=0.5), tmp_path / "x")
    # the ControlNet baseline's condition is a view from elsewhere: no residual from it
    b = ControlNetBaseline(dataclasses.replace(TINY, core=core_cfg, condition="aerial", sample_strength=0.5),
                           tmp_path / "y")
    assert not b.config.core.residual and b.config.sample_strength == 1.0


def test_training_crops_share_one_window_per_row():
    import torch

    from reference.common.diffusion.train import crops

    a = torch.arange(2 * 3 * 1 * 6 * 6, dtype=torch.float32).view(2, 3, 1, 6, 6)  # [B, F, C, h, w]
    b = -a
    ca, cb = crops(torch.Generator().manual_seed(0), 4, a, b)
    assert ca.shape == (2, 3, 1, 4, 4) and torch.equal(cb, -ca)
    for i in range(2):  # every frame of a row cut at the same window, found in the original
        hits = [(y, x) for y in range(3) for x in range(3) if torch.equal(a[i, :, :, y:y + 4, x:x + 4], ca[i])]
        assert len(hits) == 1
    assert crops(torch.Generator(), 0, a)[0] is a
    with pytest.raises(ValueError, match="exceeds"):
        crops(torch.Generator(), 7, a)


def test_device_auto_and_the_prior_follows_it(monkeypatch, tmp_path):
    import torch

    from reference.common.priors import prior_part

    m = Skyeyes(dataclasses.replace(TINY, device="auto"), tmp_path / "a")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert m.device == "cpu"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)  # what torch would report; no kernel runs
    assert m.device == "cuda"
    assert Skyeyes(dataclasses.replace(TINY, device="cuda:1"), tmp_path / "b").device == "cuda:1"
    small = PRESETS["small"]
    prior = prior_part(small.prior_method, small.prior_preset, tmp_path / "p", 0, "cuda")
    assert prior.name == "sugar" and prior.config.device == "cuda"
    assert prior_part(small.prior_method, small.prior_preset, tmp_path / "q", 0, None).config.device == "cpu"



@pytest.mark.slow  # one tiny fit, ~20 s of CPU
def test_condition_moves_its_frame_and_vcm_carries_it_across_the_clip(tiny, tmp_path):
    """Change only frame 0's condition (its prior, inverted): frame 0's output changes (the
    generator listens to its conditioning); with the VCM the later frames of its clip change too
    (they attend to the generated first frame); frame by frame (the same fitted model without
    the VCM, as SkyeyesNoVCM samples) they stay exactly as they were."""
    from reference.common.priors import frame_key

    core_cfg = dataclasses.replace(TINY.core, conditioning="concat", residual=True, residual_scale=2.0)
    m, _, out = _run(Skyeyes, tiny, tmp_path / "run", core=core_cfg)
    scene = open_dataset(tiny).split("test")[0]
    seq = next(iter(scene.sequences.values()))
    clip = slice(1, TINY.clip_frames)

    def render(vcm: bool) -> np.ndarray:
        m.config = dataclasses.replace(m.config, vcm=vcm)
        return np.stack(list(m.render_sequence(scene, seq)))

    plain = render(False)
    key = frame_key(scene, seq.frames[0])
    conds = m.scene_model(scene)  # the scene's fit: {frame key: condition}
    conds[key] = 1.0 - conds[key]
    moved, moved_plain = render(True), render(False)
    before = out[seq.id]
    assert np.abs(moved[0] - before[0]).max() > 1e-2  # the condition reaches its frame
    assert np.abs(moved_plain[0] - plain[0]).max() > 1e-2
    # VCM: frames 2..F of the clip attend to the first (6.6e-4 measured after 2 VCM steps) ...
    assert np.abs(moved[clip] - before[clip]).max() > 1e-4
    # ... frame by frame nothing but frame 0 moves.
    assert np.abs(moved_plain[clip] - plain[clip]).max() < 1e-6


def test_bf16_autocast_trains_and_samples_under_its_own_key(tiny, tmp_path):
    """`mixed_precision=bf16` on the CPU (the `small` preset): every diffusion stage trains under
    bf16 autocast with fp32 weights, the sampler calls the same autocast forward, and the stages
    are cached under other keys than an fp32 run's (their numbers differ)."""
    import torch

    from reference.common.diffusion import train

    m32, _, a = _run(Skyeyes, tiny, tmp_path / "fp32")
    m16, _, b = _run(Skyeyes, tiny, tmp_path / "bf16", mixed_precision="bf16")
    for stage in ("base", "acm", "vcm"):
        s32, s16 = m32.training[stage], m16.training[stage]
        assert (s32["mixed_precision"], s16["mixed_precision"]) == ("no", "bf16")
        assert Path(s32["checkpoint"]).parent != Path(s16["checkpoint"]).parent
        l32 = train.load_checkpoint(Path(s32["checkpoint"]))["losses"]
        l16 = train.load_checkpoint(Path(s16["checkpoint"]))["losses"]
        assert len(l16) == len(l32) and l16 != l32 and np.allclose(l16, l32, rtol=0.1, atol=0.05)
    assert all(p.dtype == torch.float32 for p in m16.acm.parameters())  # master weights stay fp32
    # the model the sampler calls computes in bf16: equal to its plain forward under autocast,
    # not to its plain forward in fp32 (the same weights)
    g = torch.Generator().manual_seed(0)
    x, k = torch.randn(2, 3, SIZE, SIZE, generator=g), torch.randn(2, 3, SIZE, SIZE, generator=g)
    t = torch.tensor([10, 900])
    with torch.no_grad():
        got = m16.acm(x, t, k)
        plain = m16.acm._original_forward  # accelerate's: the forward before `prepare` wrapped it
        with torch.autocast("cpu", dtype=torch.bfloat16):
            ref = plain(x, t, k).float()
        f32 = plain(x, t, k)
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, ref, rtol=0, atol=0)
    assert (got - f32).abs().max() > 1e-4
    for seq_id in a:
        assert np.isfinite(b[seq_id]).all() and not np.array_equal(a[seq_id], b[seq_id])


def test_geo_ablation_with_only_the_anchor_is_the_ablations_frames_anchored_to_their_renders(tiny, tmp_path):
    """`skyeyes-geo-no-vcm` with only the prior anchor on: no VCM stage, the frames of the paper's
    ablation `skyeyes-no-vcm` (the same noise and ACM), then `prior_anchor` to the frames' own
    conditions (the prior's renders): every frame differs from the ablation's, and by what the
    anchor computes from the ablation's frames alone."""
    import torch

    from reference.common.diffusion.additions import AdditionsConfig, PriorAnchorConfig
    from reference.common.diffusion.additions.anchor import prior_anchor
    from reference.common.diffusion.config import DiffusionConfig
    from reference.common.priors import frame_key
    from reference.methods.skyeyes_geo import SkyeyesGeoNoVCM

    _, _, plain = _run(SkyeyesNoVCM, tiny, tmp_path / "plain")
    geo = AdditionsConfig(**{f.name: getattr(TINY, f.name) for f in dataclasses.fields(DiffusionConfig)},
                          anchor=PriorAnchorConfig(mix=0.8, sigma_px=2.0, tiles=2))
    m, _, anchored = _run(SkyeyesGeoNoVCM, tiny, tmp_path / "anchored", config=geo)
    assert m.vcm is None and "vcm" not in m.training
    assert m.additions.names == ["prior anchor"]
    scene = open_dataset(tiny).split("test")[0]
    conds = m.scene_model(scene)
    for seq in scene.sequences.values():
        renders = torch.from_numpy(np.stack([conds[frame_key(scene, f)][..., :3] for f in seq.frames])).permute(0, 3, 1, 2)
        want = prior_anchor(torch.from_numpy(plain[seq.id]).permute(0, 3, 1, 2), renders, 2.0, 0.8, 2)
        np.testing.assert_allclose(anchored[seq.id], want.permute(0, 2, 3, 1).numpy(), atol=1e-6)
        assert (np.abs(anchored[seq.id] - plain[seq.id]).max(axis=(1, 2, 3)) > 1e-3).all()


@pytest.mark.parametrize("vcm_crop, want", [(-1, 8), (0, None), (4, 4)])
def test_vcm_trains_on_its_own_crop(tiny, tmp_path, monkeypatch, vcm_crop, want):
    """`vcm_crop` sets the VCM's training crop (-1: `train_crop`'s, 0: whole frames, what sampling
    sees) without touching the ACM's; the VCM stage's key names it only when it is set, so the
    stages cached before it existed keep their keys."""
    from reference.common.diffusion import stages, train

    seen = {"acm": set(), "vcm": set()}
    real = train.crops

    def spy(g, size, *tensors):
        out = real(g, size, *tensors)
        seen["vcm" if tensors[0].ndim == 5 else "acm"].add((size, tuple(out[0].shape[-2:])))
        return out

    keys = []
    real_ckpt = stages.stage_ckpt
    monkeypatch.setattr(train, "crops", spy)
    monkeypatch.setattr(stages, "stage_ckpt", lambda stage, key, steps: (keys.append((stage, key)),
                                                                          real_ckpt(stage, key, steps))[1])
    core_cfg = dataclasses.replace(TINY.core, conditioning="concat", residual=True, residual_scale=2.0)
    m, _, _ = _run(Skyeyes, tiny, tmp_path / "run", core=core_cfg, train_crop=8, vcm_crop=vcm_crop)
    assert seen["acm"] == {(8, (8, 8))}  # the ACM's crop whatever the VCM's
    full = (m.config.core.latent_size,) * 2  # the whole model-space frame
    assert seen["vcm"] == {(want or 0, (want, want) if want else full)}
    vcm_keys = [k for s, k in keys if s == "vcm"]
    assert vcm_keys and all(("crop" in k) == (vcm_crop >= 0) for k in vcm_keys)
    if vcm_crop >= 0:
        assert all(k["crop"] == vcm_crop for k in vcm_keys)
    with pytest.raises(ValueError, match="vcm_crop"):
        Skyeyes(dataclasses.replace(TINY, vcm_crop=-2), tmp_path / "bad")


@pytest.mark.parametrize("vcm_snr_gamma, want", [(-1.0, 5.0), (0.0, 0.0), (2.0, 2.0)])
def test_vcm_loss_weights_are_its_own(tiny, tmp_path, monkeypatch, vcm_snr_gamma, want):
    """`vcm_snr_gamma` weights the VCM's loss (-1: `snr_gamma`'s; 0: uniform) and leaves the ACM's;
    the VCM stage's key names it only when it is set."""
    from reference.common.diffusion import stages, train

    seen = {"acm": set(), "vcm": set()}
    real_acm, real_vcm = train.denoise_loss, train.clip_denoise_loss
    monkeypatch.setattr(train, "denoise_loss", lambda *a, **k: (seen["acm"].add(k["snr_gamma"]), real_acm(*a, **k))[1])
    monkeypatch.setattr(train, "clip_denoise_loss",
                        lambda *a, **k: (seen["vcm"].add(k["snr_gamma"]), real_vcm(*a, **k))[1])
    keys = []
    real_ckpt = stages.stage_ckpt
    monkeypatch.setattr(stages, "stage_ckpt", lambda stage, key, steps: (keys.append((stage, key)),
                                                                          real_ckpt(stage, key, steps))[1])
    core_cfg = dataclasses.replace(TINY.core, conditioning="concat", residual=True, residual_scale=2.0)
    _run(Skyeyes, tiny, tmp_path / "run", core=core_cfg, snr_gamma=5.0, vcm_snr_gamma=vcm_snr_gamma)
    assert seen["acm"] == {5.0}
    assert seen["vcm"] == {want}  # 0: `loss_weight`'s uniform weights
    vcm_keys = [k for s, k in keys if s == "vcm"]
    assert vcm_keys and all(k.get("snr_gamma") == (None if vcm_snr_gamma < 0 else vcm_snr_gamma) for k in vcm_keys)
    with pytest.raises(ValueError, match="vcm_snr_gamma"):
        Skyeyes(dataclasses.replace(TINY, vcm_snr_gamma=-2.0), tmp_path / "bad")
