"""DDIM sampling: frame by frame (appearance control module) and clip by clip with first-frame
conditioning (view consistency module), continued autoregressively over long sequences.

All noise comes from an explicit `torch.Generator`, so a fixed seed gives identical frames.
"""

from __future__ import annotations

import torch

from .core import ControlledUNet, device_of, sample_scheduler, sample_shape
from .vcm import clip_frames


def _scheduler(cfg, steps: int):
    # NOTE: diffusers' DDIMScheduler.step takes the previous timestep as t - T // n; with
    # trailing spacing that is the next scheduled timestep (and the last step lands on
    # alpha_bar = 1) only when n divides T. Otherwise frames would be denoised off-schedule.
    # The flow's Euler scheduler keeps its own sigma list: any count works.
    if steps < 1 or (cfg.prediction != "flow" and cfg.train_timesteps % steps):
        raise ValueError(f"DDIM steps {steps} must divide the {cfg.train_timesteps} training timesteps")
    sched = sample_scheduler(cfg)
    sched.set_timesteps(steps)
    return sched


def _is_flow(sched) -> bool:
    from diffusers import FlowMatchEulerDiscreteScheduler

    return isinstance(sched, FlowMatchEulerDiscreteScheduler)


def _start(sched, shape, generator: torch.Generator | None, strength: float, init: torch.Tensor | None,
           flow_noise: float = 1.0, noise: torch.Tensor | None = None):
    """The starting sample and the timesteps still to run. strength 1: pure noise (of std
    `flow_noise` for the flow: a residual model then starts at its prior plus that noise), every step.
    strength s < 1 (SDEdit, Meng et al. 2022): `init` (zeros when None: for a residual model,
    the condition itself) noised to the first scheduled timestep below s T, and the steps from
    there. The noise is `noise` when given (`frame_noise`), else drawn on the CPU from `generator`
    (identical frames on every device)."""
    if noise is None:
        noise = torch.randn(shape, generator=generator, device=generator.device)
    elif tuple(noise.shape) != tuple(shape):
        raise ValueError(f"noise of shape {tuple(noise.shape)} for samples of shape {tuple(shape)}")
    flow = _is_flow(sched)
    scale = flow_noise if flow else sched.init_noise_sigma
    if strength >= 1.0:
        return noise * scale, sched.timesteps
    if not 0.0 < strength:
        raise ValueError(f"strength {strength}: expected 0 < strength <= 1")
    limit = strength * sched.config.num_train_timesteps
    steps = sched.timesteps[sched.timesteps < limit]
    if len(steps) == 0:
        raise ValueError(f"strength {strength} leaves no sampling step")
    init = torch.zeros(shape, device=noise.device) if init is None else init.to(noise.device)
    return _noised(sched, init, noise, steps[0], scale), steps


def _noised(sched, z0: torch.Tensor, noise: torch.Tensor, t, scale: float) -> torch.Tensor:
    """z0 [N, ...] noised to the scheduler's timestep t with `noise` (the forward process: DDPM's
    q(z_t | z0), or the flow's straight line with noise of std `scale`)."""
    if _is_flow(sched):
        tau = float(t) / sched.config.num_train_timesteps
        return (1.0 - tau) * z0 + tau * scale * noise
    return sched.add_noise(z0, noise, torch.as_tensor(t).reshape(1).expand(z0.shape[0]))


def _step(sched, out: torch.Tensor, t, x: torch.Tensor) -> torch.Tensor:
    """One sampler step: deterministic DDIM (eta = 0), or an Euler step of the flow."""
    if _is_flow(sched):
        return sched.step(out, t, x).prev_sample
    return sched.step(out, t, x, eta=0.0).prev_sample


def _timesteps(t, n: int, dev) -> torch.Tensor:
    """The scheduler's timestep `t` for a batch of n: integer for DDIM, the flow's sigma T as is."""
    if torch.is_floating_point(torch.as_tensor(t)):
        return torch.full((n,), float(t), dtype=torch.float32, device=dev)
    return torch.full((n,), int(t), dtype=torch.long, device=dev)


def frame_noise(seed: int, shape: tuple[int, ...], batch: int = 16) -> torch.Tensor:
    """The starting noise of every frame of a sequence, [N, C, h, w] for `shape`: one CPU generator
    seeded by `seed`, drawn `batch` frames at a time (as the frame-by-frame sampler always drew it).
    Frame i's own noise depends on (seed, i, batch) alone, so the ACM frame by frame and the VCM clip
    by clip start frame i from the same noise (`skyeyes` and `skyeyes-no-vcm` are paired)."""
    g = torch.Generator().manual_seed(int(seed))
    n, rest = shape[0], tuple(shape[1:])
    # drawn on the CPU, the generator's device, on purpose: the same frames on every device
    if not n:
        return torch.zeros((0, *rest), device=g.device)
    return torch.cat([torch.randn((min(batch, n - i), *rest), generator=g, device=g.device) for i in range(0, n, batch)])


@torch.no_grad()
def ddim(model: ControlledUNet, conds: torch.Tensor | None, *, steps: int, generator: torch.Generator | None = None,
         shape: tuple[int, ...] | None = None, strength: float = 1.0,
         init: torch.Tensor | None = None, noise: torch.Tensor | None = None) -> torch.Tensor:
    """Denoise noise into model-space samples with deterministic DDIM (eta = 0).

    Args:
        conds: [N, C, h, w] conditions (model space), or None for an uncontrolled model.
        shape: [N, C, h, w] of the output when `conds` is None.
        strength, init: SDEdit start (see `_start`).
        noise: the starting noise [N, C, h, w] (`frame_noise`); else drawn from `generator`.

    Returns:
        [N, C, h, w] the generated samples (on the CPU).
    """
    sched = _scheduler(model.cfg, steps)
    shape = sample_shape(tuple(conds.shape), model.cfg) if conds is not None else tuple(shape)
    x, timesteps = _start(sched, shape, generator, strength, init, model.cfg.flow_noise, noise)
    dev = device_of(model)
    x = x.to(dev)
    c = conds.to(dev) if conds is not None else None
    for t in timesteps:
        x = _step(sched, model(x, _timesteps(t, shape[0], dev), c).float(), t, x)
    return x.cpu()


@torch.no_grad()
def sample_frames(model: ControlledUNet, conds: torch.Tensor, *, steps: int, seed: int,
                  batch: int = 16, strength: float = 1.0, noise: torch.Tensor | None = None) -> torch.Tensor:
    """ACM alone: every frame independently, frame i from `noise[i]` (default `frame_noise(seed)`).
    conds [N, C, h, w] -> [N, C, h, w]."""
    if noise is None:
        noise = frame_noise(seed, sample_shape(tuple(conds.shape), model.cfg), batch)
    out = [ddim(model, conds[i:i + batch], steps=steps, noise=noise[i:i + batch], strength=strength)
           for i in range(0, len(conds), batch)]
    return torch.cat(out)


@torch.no_grad()
def sample_sequence(acm: ControlledUNet, vcm: ControlledUNet, conds: torch.Tensor, *, steps: int,
                    seed: int, clip: int = 12, strength: float = 1.0, progress=None,
                    noise: torch.Tensor | None = None) -> torch.Tensor:
    """Skyeyes inference (Sec. 3.3 and supplement Sec. 2.2): frame 1 from the ACM alone, then
    clips of `clip` frames whose first frame is the last frame generated so far.

    conds [N, C, h, w] -> [N, C, h, w]. Each clip generates up to `clip - 1` new frames. Frame i
    starts from `noise[i]` (default `frame_noise(seed)[i]`), the noise `sample_frames` gives it:
    frame 1 is the ACM's frame exactly, and every other frame differs from the ACM's only by what
    the VCM does.
    """
    n = len(conds)
    if noise is None:
        noise = frame_noise(seed, sample_shape(tuple(conds.shape), acm.cfg))
    out = [ddim(acm, conds[:1], steps=steps, noise=noise[:1], strength=strength)[0]]
    i = 1
    while i < n:
        m = min(clip - 1, n - i)
        c = torch.cat([conds[i - 1:i], conds[i:i + m]])  # the first keeps its own prior
        out.extend(ddim_clip(vcm, c, out[-1], steps=steps, noise=noise[i:i + m], strength=strength))
        i += m
        if progress is not None:
            progress(m)
    return torch.stack(out)


@torch.no_grad()
def ddim_clip(model: ControlledUNet, conds: torch.Tensor, first: torch.Tensor, *, steps: int,
              generator: torch.Generator | None = None, strength: float = 1.0,
              noise: torch.Tensor | None = None) -> torch.Tensor:
    """One clip: conds [F, C, h, w] (the first is the given frame's), first [C, h, w] clean ->
    the F - 1 new frames [F - 1, C, h, w], from `noise` [F - 1, C, h, w] (else drawn from `generator`)."""
    sched = _scheduler(model.cfg, steps)
    f = len(conds)
    x, timesteps = _start(sched, (f - 1, *first.shape), generator, strength, None, model.cfg.flow_noise, noise)
    dev = device_of(model)
    x, first, c = x.to(dev), first.to(dev), conds.to(dev)
    with clip_frames(model, f):
        for t in timesteps:
            # 1. the clean first frame enters at timestep 0, the others at t; 2. predict the
            # clip's noise; 3. step only the frames being generated.
            tt = _timesteps(t, f, dev)
            tt[0] = 0
            out = model(torch.cat([first[None], x]), tt, c)[1:].float()
            x = _step(sched, out, t, x)
    return x.cpu()
