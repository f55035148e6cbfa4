"""Diffusion core numerics: schedule endpoints, DDIM against closed forms, ControlNet zero init,
VCM attention against a slow reference, first-frame conditioning, determinism, resume."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

import diffusers  # noqa: F401  (a hard dependency of reference: a broken install fails here, never skips)

from reference.common.diffusion import core, sample, train, vcm  # noqa: E402

TINY = core.CoreConfig(resolution=16, channels=(16, 32), attention=(False, True), head_dim=8, embed_dim=16,
                       norm_groups=4, prediction="epsilon")
TINY_V = core.replace_config(TINY, prediction="v_prediction")


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest: tiny tensors, one thread


def _alpha_bar(cfg=TINY) -> np.ndarray:
    """Closed form of the linear schedule (Ho et al. 2020), float64."""
    betas = np.linspace(cfg.beta_start, cfg.beta_end, cfg.train_timesteps, dtype=np.float64)
    return np.cumprod(1.0 - betas)


# --------------------------------------------------------------------------- schedules


def test_schedule_endpoints():
    ab = _alpha_bar()
    s = core.train_scheduler(TINY)
    np.testing.assert_allclose(s.alphas_cumprod.double().numpy(), ab, rtol=1e-5)
    assert s.alphas_cumprod[-1] < 1e-4  # pure noise at t = T, up to 1 % amplitude
    assert s.alphas_cumprod[0] > 0.9998  # t = 0 is (almost) clean
    assert s.config.prediction_type == "epsilon"
    assert core.train_scheduler(TINY_V).config.prediction_type == "v_prediction"
    assert core.CoreConfig().prediction == "v_prediction"  # the from-scratch default


def test_v_target_closed_form_and_x0_recovery():
    """v = sqrt(ab) eps - sqrt(1 - ab) x0 (Salimans & Ho 2022); x0 = sqrt(ab) x_t - sqrt(1 - ab) v."""
    ab = _alpha_bar()
    g = torch.Generator().manual_seed(0)
    x0 = torch.rand(4, 3, 4, 4, generator=g) * 2 - 1
    eps = torch.randn(4, 3, 4, 4, generator=g)
    t = torch.tensor([0, 250, 700, 999])
    a = torch.tensor(ab[t.numpy()]).view(-1, 1, 1, 1)
    sched = core.train_scheduler(TINY_V)
    v = train.target(sched, x0, eps, t).double()
    want = a.sqrt() * eps.double() - (1 - a).sqrt() * x0.double()
    np.testing.assert_allclose(v.numpy(), want.numpy(), atol=1e-5)
    x_t = a.sqrt() * x0.double() + (1 - a).sqrt() * eps.double()
    np.testing.assert_allclose((a.sqrt() * x_t - (1 - a).sqrt() * v).numpy(), x0.numpy(), atol=1e-5)
    assert torch.equal(train.target(core.train_scheduler(TINY), x0, eps, t), eps)


def test_ddim_timesteps_trailing_and_last_step_is_x0():
    s = core.sample_scheduler(TINY)
    s.set_timesteps(10)
    ts = s.timesteps.numpy()
    assert ts[0] == TINY.train_timesteps - 1  # starts at the noisiest step
    assert np.all(np.diff(ts) < 0) and ts[-1] == 99
    ab = _alpha_bar()
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 3, 4, 4, generator=g) * 0.5
    eps = torch.randn(2, 3, 4, 4, generator=g) * 0.1
    # last step (t = 99 -> "t = -1", alpha_bar = 1): DDIM returns the clipped x0 estimate
    t = int(ts[-1])
    x0 = (x.double() - np.sqrt(1 - ab[t]) * eps.double()) / np.sqrt(ab[t])
    got = s.step(eps, t, x, eta=0.0).prev_sample
    np.testing.assert_allclose(got.numpy(), x0.clamp(-1, 1).numpy(), atol=1e-5)
    # a middle step: x_prev = sqrt(ab_prev) x0 + sqrt(1 - ab_prev) eps (Song et al. 2021, eta 0)
    s.set_timesteps(10)
    t, tp = int(ts[3]), int(ts[4])
    x0 = torch.rand(2, 3, 4, 4, generator=g, dtype=torch.float64) * 1.8 - 0.9  # inside the clip range
    eps = torch.randn(2, 3, 4, 4, generator=g, dtype=torch.float64)
    x_t = np.sqrt(ab[t]) * x0 + np.sqrt(1 - ab[t]) * eps
    want = np.sqrt(ab[tp]) * x0 + np.sqrt(1 - ab[tp]) * eps
    got = s.step(eps.float(), t, x_t.float(), eta=0.0).prev_sample
    np.testing.assert_allclose(got.numpy(), want.numpy(), atol=2e-4)


def test_ddim_steps_must_divide_T():
    m = OracleModel(torch.zeros(1, 3, 4, 4))
    with pytest.raises(ValueError, match="divide"):
        sample.ddim(m, torch.zeros(1, 3, 4, 4), steps=7, generator=torch.Generator())


class OracleModel(torch.nn.Module):
    """Predicts the exact noise that leads from `target` to x_t (so DDIM must return `target`)."""

    def __init__(self, target, cfg=TINY):
        super().__init__()
        self.cfg, self.target = cfg, target
        self.ab = torch.tensor(_alpha_bar())
        self._vcm_context = vcm.ClipContext()
        self.calls = []

    def forward(self, x_t, t, cond=None):
        self.calls.append((x_t.clone(), t.clone()))
        ab = self.ab[t].view(-1, 1, 1, 1)
        n = x_t.shape[0]
        tgt = self.target[:n] if self.target.shape[0] >= n else self.target[:1].expand_as(x_t)
        eps = (x_t.double() - ab.sqrt() * tgt.double()) / (1 - ab).sqrt()
        if self.cfg.prediction == "v_prediction":
            return (ab.sqrt() * eps - (1 - ab).sqrt() * tgt.double()).float()
        return eps.float()


@pytest.mark.parametrize("cfg", [TINY, TINY_V], ids=["epsilon", "v"])
def test_ddim_loop_recovers_oracle_target(cfg):
    target = torch.rand(3, 3, 8, 8) * 1.6 - 0.8
    m = OracleModel(target, cfg)
    out = sample.ddim(m, torch.zeros(3, 3, 8, 8), steps=8, generator=torch.Generator().manual_seed(1))
    np.testing.assert_allclose(out.numpy(), target.numpy(), atol=1e-4)


def test_ddim_clip_keeps_first_frame_clean_at_t0():
    target = torch.rand(4, 3, 8, 8) * 1.6 - 0.8
    m = OracleModel(target)
    first = target[0]
    out = sample.ddim_clip(m, torch.zeros(4, 3, 8, 8), first, steps=5, generator=torch.Generator().manual_seed(0))
    assert out.shape == (3, 3, 8, 8)
    for x_t, t in m.calls:
        assert t[0] == 0 and torch.equal(x_t[0], first) and (t[1:] > 0).all()
    np.testing.assert_allclose(out.numpy(), target[1:].numpy(), atol=1e-4)


def test_sample_sequence_is_autoregressive():
    n, clip = 10, 4
    target = torch.rand(n, 3, 8, 8) * 1.6 - 0.8

    class Seq(OracleModel):
        def forward(self, x_t, t, cond):  # cond carries the frame index of each row
            self.calls.append((x_t.clone(), t.clone(), cond[:, 0, 0, 0].long().tolist()))
            ab = self.ab[t].view(-1, 1, 1, 1)
            tgt = target[cond[:, 0, 0, 0].long()]
            return ((x_t.double() - ab.sqrt() * tgt.double()) / (1 - ab).sqrt()).float()

    conds = torch.arange(n).float().view(n, 1, 1, 1).expand(n, 3, 8, 8).contiguous()
    acm, vm = Seq(target), Seq(target)
    out = sample.sample_sequence(acm, vm, conds, steps=4, seed=0, clip=clip)
    np.testing.assert_allclose(out.numpy(), target.numpy(), atol=1e-4)
    assert {tuple(c[2]) for c in acm.calls} == {(0,)}  # frame 1 from the ACM alone
    clips = sorted({tuple(c[2]) for c in vm.calls})
    assert clips == [(0, 1, 2, 3), (3, 4, 5, 6), (6, 7, 8, 9)]  # each starts from the last generated


class Shrink(OracleModel):
    """Per-frame and noise-dependent: predicts eps = x_t / 2 (each row alone), so DDIM's output
    is a fixed linear function of each frame's starting noise."""

    def forward(self, x_t, t, cond=None):
        self.calls.append((x_t.clone(), t.clone()))
        return x_t / 2


def test_frame_noise_is_the_frame_by_frame_draw():
    """`sample_frames` starts each batch from the generator's next draw, as it always did (the
    filed rows of the frame-by-frame methods stay reproducible); `frame_noise` is that draw."""
    m = Shrink(torch.zeros(1))
    c = torch.zeros(21, 3, 8, 8)
    g = torch.Generator().manual_seed(5)
    want = torch.cat([sample.ddim(m, c[i:i + 8], steps=4, generator=g) for i in range(0, 21, 8)])
    got = sample.sample_frames(m, c, steps=4, seed=5, batch=8)
    assert torch.equal(got, want)
    g = torch.Generator().manual_seed(5)
    draws = torch.cat([torch.randn(8, 3, 8, 8, generator=g), torch.randn(8, 3, 8, 8, generator=g),
                       torch.randn(5, 3, 8, 8, generator=g)])
    assert torch.equal(sample.frame_noise(5, (21, 3, 8, 8), batch=8), draws)
    with pytest.raises(ValueError, match="noise of shape"):
        sample.ddim(m, c[:2], steps=4, noise=torch.zeros(3, 3, 8, 8))


def test_sequence_sampler_is_paired_with_the_frame_sampler():
    """With a VCM that ignores the clip (a per-frame model), the clip sampler gives every frame
    exactly the frame-by-frame sampler's output: frame i starts from the same noise in both, so
    `skyeyes` minus `skyeyes-no-vcm` is the VCM's doing alone. Another seed changes the frames."""
    acm, vm = Shrink(torch.zeros(1)), Shrink(torch.zeros(1))
    # 75 values a frame: not a whole number of torch's 16-value normal blocks, so drawing a clip's
    # noise on its own (as this sampler once did) gives other numbers than the batched draw
    c = torch.zeros(30, 3, 5, 5)
    frames = sample.sample_frames(acm, c, steps=5, seed=11)
    seq = sample.sample_sequence(acm, vm, c, steps=5, seed=11, clip=12)
    torch.testing.assert_close(seq, frames, rtol=0, atol=1e-6)
    assert (frames.std(dim=0) > 0.1).all()  # the frames do differ from one another
    other = sample.sample_sequence(acm, vm, c, steps=5, seed=12, clip=12)
    assert (other - frames).abs().mean() > 0.1


# --------------------------------------------------------------------------- model


def test_controlnet_starts_as_the_unet_and_float32():
    m = core.build_model(TINY, control=False, seed=0).eval()
    x, t = torch.randn(2, 3, 16, 16), torch.tensor([10, 900])
    with torch.no_grad():
        y0 = m(x, t)
        m.add_control()
        y1 = m(x, t, torch.rand(2, 3, 16, 16))
    assert y1.dtype == torch.float32 and all(p.dtype == torch.float32 for p in m.parameters())
    torch.testing.assert_close(y1, y0, rtol=0, atol=0)  # zero convolutions
    # the branch is a copy of the UNet's encoder
    torch.testing.assert_close(m.controlnet.conv_in.weight, m.unet.conv_in.weight)


def test_build_model_is_deterministic():
    a = core.build_model(TINY, control=True, seed=3).state_dict()
    b = core.build_model(TINY, control=True, seed=3).state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_pixel_codec_roundtrip():
    cfg = core.replace_config(TINY, patch=2)
    img = torch.rand(2, 3, 16, 16)
    z = core.encode(img, cfg)
    assert z.shape == (2, 12, 8, 8) and z.min() >= -1 and z.max() <= 1
    torch.testing.assert_close(core.decode(z, cfg), img)


# --------------------------------------------------------------------------- VCM


def test_vcm_processor_matches_slow_reference():
    m = core.build_model(TINY, control=True, seed=0).eval()
    layers = vcm.self_attention_layers(m)
    assert any(n.startswith("controlnet.") for n in layers) and any(n.startswith("unet.") for n in layers)
    attn = next(iter(layers.values()))
    ctx = vcm.ClipContext(3)
    proc = vcm.ClipSelfAttnProcessor(ctx)
    x = torch.randn(6, 20, attn.to_q.in_features)  # 2 clips x 3 frames, 20 tokens
    with torch.no_grad():
        got = proc(attn, x)
        want = vcm.reference_clip_attention(attn, x, 3)
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)


def test_vcm_links_frames_only_within_a_clip():
    m = core.build_model(TINY, control=True, seed=0).eval()
    with torch.no_grad():  # make the ControlNet branch matter (its zero convs hide it otherwise)
        for p in m.controlnet.parameters():
            p.add_(torch.randn_like(p) * 0.01)
    x, t, c = torch.randn(4, 3, 16, 16), torch.full((4,), 500), torch.rand(4, 3, 16, 16)
    x2 = x.clone()
    x2[1] += 1.0  # perturb frame 2 of clip 1
    with torch.no_grad():
        plain = m(x, t, c), m(x2, t, c)
        vcm.install_vcm(m)
        one = m(x, t, c)
        with vcm.clip_frames(m, 2):
            a, b = m(x, t, c), m(x2, t, c)
    torch.testing.assert_close(one, plain[0], rtol=1e-5, atol=1e-6)  # F = 1: ordinary self-attention
    torch.testing.assert_close(plain[0][0], plain[1][0])  # without VCM frames are independent
    assert (a[0] - b[0]).abs().max() > 1e-5  # with VCM frame 1 sees frame 2 ...
    torch.testing.assert_close(a[2:], b[2:])  # ... but clip 2 does not


def test_vcm_parameters_are_attn1_projections_only():
    m = core.build_model(TINY, control=True, seed=0)
    vcm.install_vcm(m)
    params = core.trainable(m, vcm.vcm_parameter_names(m))
    names = [n for n, p in m.named_parameters() if p.requires_grad]
    assert names and all(".attn1." in n for n in names) and len(params) == len(names)
    assert {n.split(".attn1.")[1].split(".")[0] for n in names} == {"to_q", "to_k", "to_v", "to_out"}


def test_clip_loss_conditions_on_clean_first_frame():
    seen = {}

    class Rec(torch.nn.Module):
        def forward(self, x_t, t, cond):
            seen["x"], seen["t"] = x_t, t
            return torch.zeros_like(x_t)

    sched = core.train_scheduler(TINY)
    x0 = torch.rand(2, 5, 3, 8, 8)
    loss = train.clip_denoise_loss(Rec(), sched, x0, x0, torch.Generator().manual_seed(0))
    x, t = seen["x"].view(2, 5, 3, 8, 8), seen["t"].view(2, 5)
    assert torch.equal(x[:, 0], x0[:, 0]) and (t[:, 0] == 0).all()
    assert (t[:, 1:] == t[:, 1:2]).all()  # one timestep per clip
    # zero prediction: loss = mean of the squared noise of frames 2..F, recomputed from x_t
    ab = sched.alphas_cumprod[t[:, 1]].view(2, 1, 1, 1, 1)
    noise = (x[:, 1:] - ab.sqrt() * x0[:, 1:]) / (1 - ab).sqrt()
    torch.testing.assert_close(loss, noise.pow(2).mean(), rtol=1e-4, atol=1e-5)


# --------------------------------------------------------------------------- determinism, resume


def test_same_seed_same_samples():
    m = core.build_model(TINY, control=True, seed=0).eval()
    c = torch.rand(2, 3, 16, 16)
    a = sample.sample_frames(m, c, steps=4, seed=7)
    b = sample.sample_frames(m, c, steps=4, seed=7)
    d = sample.sample_frames(m, c, steps=4, seed=8)
    assert torch.equal(a, b) and not torch.equal(a, d)


def _train(tmp, stop_after=None, ckpt_every=2):
    m = core.build_model(TINY, control=False, seed=0)
    sched = core.train_scheduler(TINY)
    data = torch.rand(6, 3, 16, 16, generator=torch.Generator().manual_seed(0)) * 2 - 1
    params = core.trainable(m)

    def loss_fn(net, g, part):
        idx = torch.randint(0, 6, (2,), generator=g)
        return train.denoise_loss(net, sched, data[idx], None, g, part=part)

    res = train.train_loop(m, params, loss_fn, steps=5, lr=1e-3, seed=0, ckpt=tmp / "c.pt",
                           ckpt_every=ckpt_every, stop_after=stop_after, progress=False)
    return m, res


def test_killed_training_resumes_to_identical_weights(tmp_path):
    full, r_full = _train(tmp_path / "full")
    _, r1 = _train(tmp_path / "killed", stop_after=3)  # "killed" after step 3; last checkpoint at 2
    assert not r1["done"] and r1["steps"] == 3
    assert train.load_checkpoint(tmp_path / "killed" / "c.pt")["step"] == 2
    resumed, r2 = _train(tmp_path / "killed")
    assert r2["done"] and r2["steps"] == 5
    a, b = full.state_dict(), resumed.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert r2["losses"][:2] == r_full["losses"][:2] and len(r2["losses"]) == 5
    assert sorted(p.name for p in (tmp_path / "killed").iterdir()) == ["c.pt"]  # no temp files left


def test_anneal_factor_closed_form():
    assert [train.anneal_factor(s, 3, 7) for s in range(7)] == [1, 1, 1, 1.0, 0.75, 0.5, 0.25]
    assert train.anneal_factor(0, 0, 1) == 1.0  # a one-step decay still takes its step


def test_annealed_training_is_adamw_under_torch_linear_lr(tmp_path):
    """The decay phase equals a hand-written loop: AdamW, gradient clipping at 1 and torch's own
    LinearLR from factor 1 to 1/n over the n decay steps; and a killed annealed run resumes to
    the same weights."""
    steps, start = 6, 2
    m = core.build_model(TINY, control=False, seed=0)
    sched = core.train_scheduler(TINY)
    data = torch.rand(6, 3, 16, 16, generator=torch.Generator().manual_seed(0)) * 2 - 1

    def loss_fn(net, g, part=(0, 1)):
        idx = torch.randint(0, 6, (2,), generator=g)
        return train.denoise_loss(net, sched, data[idx], None, g, part=part)

    ref = core.build_model(TINY, control=False, seed=0)
    params = core.trainable(ref)
    opt = torch.optim.AdamW(params, lr=1e-2, weight_decay=0.0)
    lin = torch.optim.lr_scheduler.LinearLR(opt, start_factor=1.0, end_factor=1 / (steps - start),
                                            total_iters=steps - start - 1)
    for step in range(steps):
        loss = loss_fn(ref, train.step_generator(0, step))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        if step >= start:
            lin.step()
    run = dict(steps=steps, lr=1e-2, seed=0, anneal_from=start, progress=False, ckpt_every=2)
    train.train_loop(m, core.trainable(m), loss_fn, ckpt=tmp_path / "a.pt", **run)
    a, b = m.state_dict(), ref.state_dict()
    assert all(torch.allclose(a[k], b[k], rtol=1e-5, atol=1e-7) for k in a)
    const = core.build_model(TINY, control=False, seed=0)  # the decay matters: constant differs
    train.train_loop(const, core.trainable(const), loss_fn, ckpt=tmp_path / "c.pt", **{**run, "anneal_from": None})
    assert any((const.state_dict()[k] - a[k]).abs().max() > 1e-6 for k in a)
    killed = core.build_model(TINY, control=False, seed=0)
    train.train_loop(killed, core.trainable(killed), loss_fn, ckpt=tmp_path / "k.pt", stop_after=5, **run)
    assert train.load_checkpoint(tmp_path / "k.pt")["step"] == 4  # mid-decay
    resumed = core.build_model(TINY, control=False, seed=0)
    train.train_loop(resumed, core.trainable(resumed), loss_fn, ckpt=tmp_path / "k.pt", **run)
    assert all(torch.equal(resumed.state_dict()[k], a[k]) for k in a)


# --------------------------------------------------------------------------- CPU formulation (issue 13)

CONCAT = core.replace_config(TINY_V, conditioning="concat", residual=True, residual_scale=2.0)


def test_concat_model_sees_its_condition_from_the_first_step():
    """The condition enters at the input: an untrained model's output already depends on it
    (a fresh ControlNet branch's zero convolutions hide it, the test below that)."""
    m = core.build_model(CONCAT, control=True, seed=0).eval()
    assert m.unet.conv_in.in_channels == 6 and m.unet.conv_out.out_channels == 3 and m.controlnet is None
    x, t = torch.randn(2, 3, 16, 16), torch.full((2,), 500)
    with torch.no_grad():
        a, b = m(x, t, torch.zeros(2, 3, 16, 16)), m(x, t, torch.ones(2, 3, 16, 16))
    assert (a - b).abs().max() > 1e-4
    with pytest.raises(AssertionError, match="condition"):
        m(x, t, None)
    c = core.build_model(TINY_V, control=True, seed=0).eval()
    with torch.no_grad():
        torch.testing.assert_close(c(x, t, torch.zeros(2, 3, 16, 16)), c(x, t, torch.ones(2, 3, 16, 16)))
    with pytest.raises(ValueError, match="concat"):
        core.replace_config(TINY, residual=True)
    with pytest.raises(ValueError, match="conditioning"):
        core.replace_config(TINY, conditioning="crossattn")


def test_residual_round_trip_and_its_range_is_not_clipped():
    """z = (x0 - c) k; the sampler's x0 clip for a residual spans [-2k, 2k], not [-1, 1]."""
    g = torch.Generator().manual_seed(0)
    x0, c = torch.rand(3, 3, 8, 8, generator=g) * 2 - 1, torch.rand(3, 3, 8, 8, generator=g) * 2 - 1
    z = core.to_diffused(x0, c, CONCAT)
    torch.testing.assert_close(z, (x0 - c) * 2.0)
    torch.testing.assert_close(core.from_diffused(z, c, CONCAT), x0)
    assert torch.equal(core.to_diffused(x0, c, TINY_V), x0)  # no residual: the frames themselves
    target = torch.rand(3, 3, 8, 8, generator=g) * 7 - 3.5  # residuals up to |3.5| (k = 2)
    out = sample.ddim(OracleModel(target, CONCAT), c, steps=8, generator=torch.Generator().manual_seed(1))
    np.testing.assert_allclose(out.numpy(), target.numpy(), atol=1e-4)
    clipped = sample.ddim(OracleModel(target, TINY_V), c, steps=8, generator=torch.Generator().manual_seed(1))
    assert clipped.abs().max() <= 1.0 + 1e-6  # a frame model clips to the image range


def test_sdedit_start_noises_the_prior_to_the_strength():
    """strength s: the first step is the first scheduled timestep below s T, from
    x = sqrt(1 - ab_t) noise (the residual of the prior is zero) with the same noise draw."""
    ab = _alpha_bar()
    sched = sample._scheduler(CONCAT, 10)  # trailing: 999, 899, ..., 99
    x, steps = sample._start(sched, (2, 3, 4, 4), torch.Generator().manual_seed(3), 0.5, None)
    assert steps.tolist() == [499, 399, 299, 199, 99]
    noise = torch.randn((2, 3, 4, 4), generator=torch.Generator().manual_seed(3))
    np.testing.assert_allclose(x.numpy(), (np.sqrt(1 - ab[499]) * noise.double()).numpy(), rtol=1e-5, atol=1e-6)
    target = torch.rand(2, 3, 8, 8) * 2 - 1
    m = OracleModel(target, CONCAT)
    out = sample.ddim(m, torch.zeros(2, 3, 8, 8), steps=10, generator=torch.Generator().manual_seed(1), strength=0.5)
    np.testing.assert_allclose(out.numpy(), target.numpy(), atol=1e-4)
    assert [int(t[0]) for _, t in m.calls] == [499, 399, 299, 199, 99]
    for bad in (0.0, -1.0, 0.05):  # 0.05 T = 50 < the last step 99: no step left
        with pytest.raises(ValueError, match="strength"):
            sample._start(sched, (1, 3, 4, 4), torch.Generator(), bad, None)


def test_min_snr_weights_closed_form():
    """Hang et al. 2023: w = min(SNR, g) / (SNR + 1) for v, min(SNR, g) / SNR for epsilon."""
    ab = _alpha_bar()
    t = torch.tensor([0, 100, 300, 600, 999])
    snr = ab[t.numpy()] / (1 - ab[t.numpy()])
    for cfg, want in ((TINY_V, np.minimum(snr, 5.0) / (snr + 1)), (TINY, np.minimum(snr, 5.0) / snr)):
        got = train.loss_weight(core.train_scheduler(cfg), t, 5.0)
        np.testing.assert_allclose(got.numpy(), want, rtol=5e-4)  # the schedule is float32
    assert torch.equal(train.loss_weight(core.train_scheduler(TINY), t, None), torch.ones(5))
    # weighted loss = mean over rows of w_t * per-row squared error
    x0 = torch.rand(4, 3, 8, 8) * 2 - 1

    class Zero(torch.nn.Module):
        def forward(self, x_t, t, cond):
            return torch.zeros_like(x_t)

    s = core.train_scheduler(TINY)
    g1, g2 = torch.Generator().manual_seed(9), torch.Generator().manual_seed(9)
    tt = torch.randint(0, 1000, (4,), generator=g2)
    noise = torch.randn(x0.shape, generator=g2)
    want = (train.loss_weight(s, tt, 5.0) * noise.pow(2).flatten(1).mean(1)).mean()
    torch.testing.assert_close(train.denoise_loss(Zero(), s, x0, None, g1, snr_gamma=5.0), want)


def test_batch_share_of_a_process():
    """Process r of w takes rows [r B/w, (r + 1) B/w) of the global draw; shares tile it."""
    x0 = torch.rand(6, 3, 8, 8) * 2 - 1
    seen = []

    class Rec(torch.nn.Module):
        def forward(self, x_t, t, cond):
            seen.append(t.clone())
            return torch.zeros_like(x_t)

    s = core.train_scheduler(TINY)
    whole = train.denoise_loss(Rec(), s, x0, None, torch.Generator().manual_seed(4))
    parts = [train.denoise_loss(Rec(), s, x0, None, torch.Generator().manual_seed(4), part=(r, 3)) for r in range(3)]
    assert torch.equal(torch.cat(seen[1:]), seen[0])
    torch.testing.assert_close(torch.stack(parts).mean(), whole)
    # a batch the processes do not divide (issue 34: the paper's 2 VCM clips over 4 GPUs): shares
    # of ceil(B/w) rows, a process left without rows computes one at weight 0, and the mean of
    # the processes' losses (what data-parallel gradients average) is still the whole batch's
    for world in (4, 5, 8):
        seen.clear()
        whole = train.denoise_loss(Rec(), s, x0, None, torch.Generator().manual_seed(4))
        parts = [train.denoise_loss(Rec(), s, x0, None, torch.Generator().manual_seed(4), part=(r, world))
                 for r in range(world)]
        k = -(-6 // world)
        rows = [min(k, max(0, 6 - r * k)) for r in range(world)]
        assert [len(t) for t in seen[1:]] == [n or 1 for n in rows]  # weight-0 row where none is left
        assert torch.equal(torch.cat([t for t, n in zip(seen[1:], rows) if n]), seen[0])
        torch.testing.assert_close(torch.stack(parts).mean(), whole)
        assert all(float(p) == 0.0 for p, n in zip(parts, rows) if not n)


def test_clip_loss_share_of_a_process_where_the_batch_does_not_split():
    """2 clips over 4 processes: the mean of the processes' clip losses is the whole batch's."""
    m = core.build_model(TINY, control=True, seed=0)
    vcm.install_vcm(m)
    s = core.train_scheduler(TINY)
    g = torch.Generator().manual_seed(0)
    x0 = torch.rand(2, 3, 3, 16, 16, generator=g) * 2 - 1  # [B, F, C, h, w]
    cond = torch.rand(2, 3, 3, 16, 16, generator=g) * 2 - 1
    with torch.no_grad(), vcm.clip_frames(m, 3):
        whole = train.clip_denoise_loss(m, s, x0, cond, torch.Generator().manual_seed(1))
        parts = [train.clip_denoise_loss(m, s, x0, cond, torch.Generator().manual_seed(1), part=(r, 4))
                 for r in range(4)]
    torch.testing.assert_close(torch.stack(parts).mean(), whole, rtol=1e-5, atol=1e-7)
    assert float(parts[2]) == float(parts[3]) == 0.0


def test_vcm_sits_in_the_unet_down_and_up_blocks_only():
    """Skyeyes Sec. 3.3: VCM in the LDM's down- and up-sampling blocks; the middle block and the
    ControlNet branch (the frozen ACM) keep per-frame self-attention."""
    m = core.build_model(TINY, control=True, seed=0)
    before = {n: type(a.processor) for n, a in vcm.self_attention_layers(m).items()}
    assert any(".mid_block." in n for n in before) and any(n.startswith("controlnet.") for n in before)
    vcm.install_vcm(m)
    for n, a in vcm.self_attention_layers(m).items():
        rewired = isinstance(a.processor, vcm.ClipSelfAttnProcessor)
        assert rewired == n.startswith(("unet.down_blocks.", "unet.up_blocks.")), n
    names = [n for n, p in m.named_parameters() if n.startswith(tuple(vcm.vcm_parameter_names(m)))]
    assert names and not any(".mid_block." in n or n.startswith("controlnet.") for n in names)


def test_device_and_precision_resolution(monkeypatch):
    """--device auto is CUDA when present; mixed precision is bf16 (fp16 without bf16) on CUDA,
    none on the CPU (no GPU needed: the choice is a pure function of what torch reports)."""
    assert train.precision_for("cpu", "auto", cuda=False, bf16=False) == "no"
    assert train.precision_for("cuda", "auto", cuda=True, bf16=True) == "bf16"
    assert train.precision_for("cuda:1", "auto", cuda=True, bf16=False) == "fp16"
    assert train.precision_for("cuda", "no", cuda=True, bf16=True) == "no"
    with pytest.raises(ValueError, match="mixed precision"):
        train.precision_for("cpu", "fp8", cuda=False, bf16=False)
    acc = train.make_accelerator("cpu", "auto")
    assert acc.device.type == "cpu" and acc.mixed_precision == "no"


def test_a_cpu_stage_after_another_device_stage_in_one_process_runs_on_the_cpu():
    """accelerate keeps the device in a per-process PartialState: on an H200 a CPU stage built
    after a CUDA one in the same process trained on CUDA (docs/log/runs-2026.md). Without a GPU, a state
    left on another device (meta stands in for cuda) must not leak into the next accelerator."""
    from accelerate.state import PartialState

    train.make_accelerator("cpu", "no")
    PartialState._shared_state["device"] = torch.device("meta")  # what a CUDA stage leaves behind
    try:
        acc = train.make_accelerator("cpu", "no")
        assert acc.device.type == "cpu"
    finally:
        train.make_accelerator("cpu", "no")


def test_coordinate_channels_locate_a_crop_in_the_frame():
    """With `coords` the condition carries x, y in [-1, 1] over the whole frame (checked against
    numpy's linspace), a crop of it carries the crop's own place, the model takes them as two
    more input channels, and the residual uses the image channels only."""
    from reference.common.diffusion.train import crops

    cfg = core.replace_config(CONCAT, coords=True)
    assert cfg.cond_channels == 5 and cfg.in_channels == 8
    img = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(0))
    c = core.encode_cond(img, cfg)
    assert c.shape == (2, 5, 16, 16)
    torch.testing.assert_close(c[:, :3], img * 2 - 1)
    lin = np.linspace(-1, 1, 16)
    np.testing.assert_allclose(c[1, 3].numpy(), np.tile(lin, (16, 1)), atol=1e-6)  # x varies along columns
    np.testing.assert_allclose(c[1, 4].numpy(), np.tile(lin[:, None], (1, 16)), atol=1e-6)
    (crop,) = crops(torch.Generator().manual_seed(3), 8, c)
    for i in range(2):  # each crop's coordinates name the window it was cut from
        x0 = int(np.argmin(np.abs(lin - float(crop[i, 3, 0, 0]))))
        y0 = int(np.argmin(np.abs(lin - float(crop[i, 4, 0, 0]))))
        torch.testing.assert_close(crop[i], c[i, :, y0:y0 + 8, x0:x0 + 8])
    assert core.sample_shape(tuple(c.shape), cfg) == (2, 3, 16, 16)
    x0 = torch.rand(2, 3, 16, 16) * 2 - 1
    z = core.to_diffused(x0, c, cfg)
    torch.testing.assert_close(z, (x0 - c[:, :3]) * 2.0)
    torch.testing.assert_close(core.from_diffused(z, c, cfg), x0)
    m = core.build_model(cfg, control=True, seed=0).eval()
    assert m.unet.conv_in.in_channels == 8
    t = torch.full((2,), 500)
    with torch.no_grad():
        a = m(z, t, c)
        flipped = c.clone()
        flipped[:, 3:] = -flipped[:, 3:]
        assert (a - m(z, t, flipped)).abs().max() > 1e-4  # the coordinates reach the output
    with pytest.raises(AssertionError, match="cond_channels"):
        m(z, t, c[:, :3])
    with pytest.raises(ValueError, match="coordinate"):
        core.replace_config(TINY, coords=True)


# --------------------------------------------------------------------------- rectified flow

TINY_FLOW = core.replace_config(TINY, prediction="flow", flow_noise=0.3)


class FlowOracle(torch.nn.Module):
    """The exact velocity of the straight path from `target` through x_t: (x_t - target) / tau,
    tau = t / T (so Euler steps on the flow's schedule must land on `target` exactly)."""

    def __init__(self, target, cfg=TINY_FLOW):
        super().__init__()
        self.cfg, self.target = cfg, target
        self._vcm_context = vcm.ClipContext()
        self.calls = []

    def forward(self, x_t, t, cond=None):
        self.calls.append((x_t.clone(), t.clone()))
        tau = (t.double() / self.cfg.train_timesteps).view(-1, 1, 1, 1)
        tgt = self.target[:x_t.shape[0]].double()
        v = torch.where(tau > 0, (x_t.double() - tgt) / tau.clamp(min=1e-12), torch.zeros_like(tgt))
        return v.float()


def test_flow_training_pair_closed_form():
    """z_tau = (1 - tau) z0 + tau s eps and the velocity s eps - z0, tau = t / T; t drawn in 1..T."""
    s = core.train_scheduler(TINY_FLOW)
    g = torch.Generator().manual_seed(0)
    x0, eps = torch.randn(4, 3, 4, 4, generator=g), torch.randn(4, 3, 4, 4, generator=g)
    t = torch.tensor([0, 1, 500, 1000])
    tau = np.array([0.0, 0.001, 0.5, 1.0]).reshape(-1, 1, 1, 1)
    z = s.add_noise(x0, eps, t).double().numpy()
    np.testing.assert_allclose(z, (1 - tau) * x0.double().numpy() + tau * 0.3 * eps.double().numpy(), atol=1e-6)
    np.testing.assert_array_equal(z[0], x0[0].numpy())  # t = 0: the clean sample (a clip's first frame)
    np.testing.assert_allclose(train.target(s, x0, eps, t).numpy(), (0.3 * eps - x0).numpy(), atol=1e-6)
    drawn = train.draw_timesteps(s, 20000, torch.Generator().manual_seed(1))
    assert int(drawn.min()) == 1 and int(drawn.max()) == TINY.train_timesteps
    assert torch.equal(train.loss_weight(s, t, 5.0), torch.ones(4))  # min-SNR is a DDPM weighting
    with pytest.raises(ValueError, match="prediction"):
        core.replace_config(TINY, prediction="x0")
    with pytest.raises(ValueError, match="flow_noise"):
        core.replace_config(TINY, prediction="flow", flow_noise=0.0)


@pytest.mark.parametrize("steps", [1, 7, 10])
def test_flow_sampler_lands_on_oracle_target_from_scaled_noise(steps):
    target = torch.rand(3, 3, 8, 8) * 1.6 - 0.8
    m = FlowOracle(target)
    out = sample.ddim(m, torch.zeros(3, 3, 8, 8), steps=steps, generator=torch.Generator().manual_seed(1))
    np.testing.assert_allclose(out.numpy(), target.numpy(), atol=1e-4)
    noise = torch.randn((3, 3, 8, 8), generator=torch.Generator().manual_seed(1))
    x_first, t_first = m.calls[0]
    np.testing.assert_allclose(x_first.numpy(), (0.3 * noise).numpy(), atol=1e-6)  # tau = 1: noise of std 0.3
    assert float(t_first[0]) == TINY.train_timesteps and len(m.calls) == steps
    ts = [float(t[0]) for _, t in m.calls]
    assert all(a > b for a, b in zip(ts, ts[1:]))


def test_flow_sdedit_start_and_clip_first_frame():
    target = torch.rand(4, 3, 8, 8) * 1.6 - 0.8
    sched = sample._scheduler(TINY_FLOW, 10)
    x, steps = sample._start(sched, (2, 3, 8, 8), torch.Generator().manual_seed(3), 0.5, target[:2], 0.3)
    tau = float(steps[0]) / TINY.train_timesteps
    assert 0.4 < tau < 0.5 and len(steps) == 5
    noise = torch.randn((2, 3, 8, 8), generator=torch.Generator().manual_seed(3))
    np.testing.assert_allclose(x.numpy(), ((1 - tau) * target[:2] + tau * 0.3 * noise).numpy(), atol=1e-6)
    m = FlowOracle(target)
    out = sample.ddim_clip(m, torch.zeros(4, 3, 8, 8), target[0], steps=5, generator=torch.Generator().manual_seed(0))
    for x_t, t in m.calls:
        assert float(t[0]) == 0 and torch.equal(x_t[0], target[0]) and (t[1:] > 0).all()
    np.testing.assert_allclose(out.numpy(), target[1:].numpy(), atol=1e-4)


def test_core_key_holds_flow_noise_only_for_the_flow():
    """A DDPM stage's key does not change with flow_noise (no effect on it; keeps the keys of
    stages trained before the field existed); a flow stage's key does."""
    a, b = core.replace_config(TINY_V, flow_noise=0.3), core.replace_config(TINY_V, flow_noise=1.0)
    assert core.core_key(a) == core.core_key(b) and "flow_noise" not in core.core_key(a)
    assert core.core_key(TINY_FLOW) != core.core_key(core.replace_config(TINY_FLOW, flow_noise=1.0))
    assert core.core_key(TINY_V) != core.core_key(TINY)  # every other field counts


def test_micro_batches_and_checkpointing_train_as_one_pass(tmp_path):
    """Issue 34 (memory for batch on a GPU): a step's share in micro-batches, gradients
    accumulated, and activation checkpointing give one pass's weights up to float rounding."""
    def fit(name, micro=1, checkpointing=False, batch=4):
        model = core.build_model(TINY, control=True, seed=0)
        if checkpointing:
            model.unet.enable_gradient_checkpointing()
            model.controlnet.enable_gradient_checkpointing()
        s = core.train_scheduler(TINY)
        g = torch.Generator().manual_seed(2)
        x0 = torch.rand(8, 3, 16, 16, generator=g) * 2 - 1
        cond = torch.rand(8, 3, 16, 16, generator=g) * 2 - 1

        def loss_fn(net, gen, part):
            idx = torch.randint(0, 8, (batch,), generator=gen, device=gen.device)
            return train.denoise_loss(net, s, x0[idx], cond[idx], gen, part=part, snr_gamma=5.0)

        res = train.train_loop(model, core.trainable(model), loss_fn, steps=3, lr=1e-2, seed=0,
                               ckpt=tmp_path / name / "c.pt", progress=False, micro_batches=micro)
        return model.state_dict(), res["losses"]

    one, l1 = fit("one")
    init = core.build_model(TINY, control=True, seed=0).state_dict()
    moved = max(float((one[k] - init[k]).abs().max()) for k in one)
    for name, kw in (("micro2", dict(micro=2)), ("micro4", dict(micro=4)), ("micro3", dict(micro=3)),
                     ("ckpt", dict(checkpointing=True))):
        other, losses = fit(name, **kw)
        assert losses == pytest.approx(l1, rel=1e-5), name
        assert max(float((other[k] - one[k]).abs().max()) for k in one) < 0.02 * moved, name
    # and the comparison can fail: one pass at another batch ends elsewhere
    half, _ = fit("half", batch=2)
    assert max(float((half[k] - one[k]).abs().max()) for k in one) > 0.3 * moved


@pytest.mark.slow  # inductor compiles the UNet's forward and backward: about a minute on 2 cores
@pytest.mark.skipif(not (shutil.which("g++") or shutil.which("c++")),
                    reason="torch.compile on the CPU (inductor) needs a C++ compiler")
def test_a_compiled_network_trains_as_the_eager_one(tmp_path):
    """`compile` (issue 34, the launch overhead of a small model on a GPU): the steps of a
    torch.compile'd network are the eager steps up to float rounding, and the checkpoint holds
    the plain module's weights (a resumed eager run reads it)."""
    def fit(name, mode="", steps=3):
        model = core.build_model(TINY, control=True, seed=0)
        s = core.train_scheduler(TINY)
        g = torch.Generator().manual_seed(2)
        x0 = torch.rand(8, 3, 16, 16, generator=g) * 2 - 1
        cond = torch.rand(8, 3, 16, 16, generator=g) * 2 - 1

        def loss_fn(net, gen, part):
            idx = torch.randint(0, 8, (4,), generator=gen, device=gen.device)
            return train.denoise_loss(net, s, x0[idx], cond[idx], gen, part=part, snr_gamma=5.0)

        res = train.train_loop(model, core.trainable(model), loss_fn, steps=steps, lr=1e-2, seed=0,
                               ckpt=tmp_path / name / "c.pt", progress=False, compile_mode=mode)
        return model.state_dict(), res

    from torch._dynamo.utils import counters

    eager, r_eager = fit("eager")
    counters.clear()
    compiled, r_comp = fit("compiled", "default")
    assert counters["stats"]["unique_graphs"] > 0  # it did compile (the comparison below can fail)
    assert r_comp["losses"] == pytest.approx(r_eager["losses"], rel=1e-4)
    init = core.build_model(TINY, control=True, seed=0).state_dict()
    moved = max(float((eager[k] - init[k]).abs().max()) for k in eager)
    assert max(float((compiled[k] - eager[k]).abs().max()) for k in eager) < 0.02 * moved
    state = train.load_checkpoint(tmp_path / "compiled" / "c.pt")["model"]
    assert state.keys() == eager.keys()  # the plain module's names, no `_orig_mod.` prefix
    resumed, r_res = fit("compiled", "", steps=4)  # an eager run resumes the compiled one
    assert r_res["resumed_seconds"] > 0 and len(r_res["losses"]) == 4


def test_compile_mode_is_checked():
    import dataclasses

    from reference.common.diffusion import pipeline
    from reference.methods.skyeyes import PRESETS

    with pytest.raises(ValueError, match="compile 'fast'"):
        pipeline.adapted(dataclasses.replace(PRESETS["smoke"], compile="fast"), "controlnet")
    assert pipeline.adapted(dataclasses.replace(PRESETS["smoke"], compile="reduce-overhead"), "controlnet").compile
