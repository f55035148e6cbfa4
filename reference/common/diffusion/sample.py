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


def frame_noise(seed: int, shape: tuple[int, ...], batch: int = 16, share: float = 0.0,
                sigma: float = 0.0) -> torch.Tensor:
    """The starting noise of every frame of a sequence, [N, C, h, w] for `shape`: one CPU generator
    seeded by `seed`, drawn `batch` frames at a time (as the frame-by-frame sampler always drew it).
    Frame i's own noise depends on (seed, i, batch) alone, so the ACM frame by frame and the VCM clip
    by clip start frame i from the same noise (`skyeyes` and `skyeyes-no-vcm` are paired).

    share (`vcm_noise`, 0 <= share <= 1): every frame's noise is sqrt(share) of one draw the
    sequence shares (its own generator, seeded by `seed`) plus sqrt(1 - share) of its own, so each
    frame's noise is still exactly a standard normal and only its correlation across frames changes
    (share 0: independent frames; 1: one noise for the whole sequence). sigma > 0
    (`vcm_noise_sigma`, model-space pixels): only the low frequencies are shared: at spatial
    frequency f the shared part's weight is share * exp(-2 pi^2 sigma^2 |f|^2) (a Gaussian low-pass
    of std sigma), the frame's own the rest, so the noise stays white (the low-frequency noise
    re-initialisation of FreeInit, Wu et al. 2023, across frames instead of across iterations)."""
    if not 0.0 <= share <= 1.0 or sigma < 0:
        raise ValueError(f"noise share {share}, sigma {sigma}: expected 0 <= share <= 1, sigma >= 0")
    g = torch.Generator().manual_seed(int(seed))
    n, rest = shape[0], tuple(shape[1:])
    # drawn on the CPU, the generator's device, on purpose: the same frames on every device
    own = torch.cat([torch.randn((min(batch, n - i), *rest), generator=g, device=g.device)
                     for i in range(0, n, batch)]) if n else torch.zeros((0, *rest), device=g.device)
    if share == 0.0:
        return own
    common = torch.randn((1, *rest), generator=torch.Generator().manual_seed(int(seed) + SHARED_SALT))
    if sigma == 0.0:
        return share ** 0.5 * common + (1.0 - share) ** 0.5 * own
    fy, fx = (torch.fft.fftfreq(k, dtype=torch.float64) for k in rest[-2:])
    w = share * torch.exp(-2.0 * torch.pi ** 2 * sigma ** 2 * (fy[:, None] ** 2 + fx[None, :] ** 2))
    mixed = w.sqrt() * torch.fft.fft2(common.double()) + (1.0 - w).sqrt() * torch.fft.fft2(own.double())
    return torch.fft.ifft2(mixed).real.float()  # w is even in f, so the imaginary part is rounding


#: Offsets the seed of a sequence's shared noise from its frames' own (`frame_noise`).
SHARED_SALT = 0x5EED_C0DE


@torch.no_grad()
def ddim(model: ControlledUNet, conds: torch.Tensor | None, *, steps: int, generator: torch.Generator | None = None,
         shape: tuple[int, ...] | None = None, strength: float = 1.0,
         init: torch.Tensor | None = None, noise: torch.Tensor | None = None,
         held: tuple[torch.Tensor, torch.Tensor] | None = None, hold: int = 0) -> torch.Tensor:
    """Denoise noise into model-space samples with deterministic DDIM (eta = 0).

    Args:
        conds: [N, C, h, w] conditions (model space), or None for an uncontrolled model.
        shape: [N, C, h, w] of the output when `conds` is None.
        strength, init: SDEdit start (see `_start`).
        noise: the starting noise [N, C, h, w] (`frame_noise`); else drawn from `generator`.
        held, hold: targets held for the first steps (`_hold`).

    Returns:
        [N, C, h, w] the generated samples (on the CPU).
    """
    sched = _scheduler(model.cfg, steps)
    shape = sample_shape(tuple(conds.shape), model.cfg) if conds is not None else tuple(shape)
    x, timesteps = _start(sched, shape, generator, strength, init, model.cfg.flow_noise, noise)
    dev = device_of(model)
    x = x.to(dev)
    c = conds.to(dev) if conds is not None else None
    for k, t in enumerate(timesteps):
        x = _step(sched, model(x, _timesteps(t, shape[0], dev), c).float(), t, x)
        x = _hold(sched, x, k, timesteps, held, hold, noise, model.cfg)
    return x.cpu()


def _hold(sched, x: torch.Tensor, k: int, timesteps, held, hold: int, noise, cfg) -> torch.Tensor:
    """After step k of the first `hold`: where held's mask is 1, x is held's target noised to the
    next timestep with the samples' own starting `noise` (the target itself after the last step;
    `warp.WarpTargets` makes them). held: (targets, masks) of x's shape, or None."""
    if held is None or k >= hold:
        return x
    if noise is None:
        raise ValueError("held samples need their starting noise")
    target, mask = (h.to(x.device) for h in held)
    scale = cfg.flow_noise if _is_flow(sched) else 1.0
    nxt = _noised(sched, target, noise.to(x.device), timesteps[k + 1], scale) if k + 1 < len(timesteps) else target
    return mask * nxt + (1.0 - mask) * x


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
                    warp=None, hold: int = 0, noise: torch.Tensor | None = None, align=None) -> torch.Tensor:
    """Skyeyes inference (Sec. 3.3 and supplement Sec. 2.2): frame 1 from the ACM alone, then
    clips of `clip` frames whose first frame is the last frame generated so far.

    conds [N, C, h, w] -> [N, C, h, w]. Each clip generates up to `clip - 1` new frames. Frame i
    starts from `noise[i]` (default `frame_noise(seed)[i]`), the noise `sample_frames` gives it:
    frame 1 is the ACM's frame exactly, and every other frame differs from the ACM's only by what
    the VCM does.
    `warp` (`warp.WarpTargets`) and `hold`: the clip's first frame, warped into each new frame,
    holds the pixels it reaches for the first `hold` steps (`ddim_clip`). `vcm` None: every frame
    from the ACM alone, one at a time, held by the previous frame's warp (`ddim`).
    `align` (`warp.FlowAlign`): the clip's first frame enters moved into its second frame's view,
    on that frame's condition (`vcm_align`).
    """
    n = len(conds)
    if noise is None:
        noise = frame_noise(seed, sample_shape(tuple(conds.shape), acm.cfg))
    out = [ddim(acm, conds[:1], steps=steps, noise=noise[:1], strength=strength)[0]]
    i = 1
    while i < n:
        m = 1 if vcm is None else min(clip - 1, n - i)  # no VCM: the ACM, one frame at a time
        held = warp(out[-1], i - 1, list(range(i, i + m))) if warp is not None and hold > 0 else None
        if vcm is None:
            new = ddim(acm, conds[i:i + 1], steps=steps, noise=noise[i:i + 1], strength=strength,
                       held=held, hold=hold)
        else:
            if align is None:
                first, c = out[-1], torch.cat([conds[i - 1:i], conds[i:i + m]])  # the first keeps its own prior
            else:
                first, c = align(out[-1], i - 1, i), torch.cat([conds[i:i + 1], conds[i:i + m]])
            new = ddim_clip(vcm, c, first, steps=steps, noise=noise[i:i + m], strength=strength,
                            held=held, hold=hold)
        out.extend(new)
        i += m
        if progress is not None:
            progress(m)
    return torch.stack(out)


@torch.no_grad()
def ddim_clip(model: ControlledUNet, conds: torch.Tensor, first: torch.Tensor, *, steps: int,
              generator: torch.Generator | None = None, strength: float = 1.0,
              noise: torch.Tensor | None = None,
              held: tuple[torch.Tensor, torch.Tensor] | None = None, hold: int = 0) -> torch.Tensor:
    """One clip: conds [F, C, h, w] (the first is the given frame's), first [C, h, w] clean ->
    the F - 1 new frames [F - 1, C, h, w], from `noise` [F - 1, C, h, w] (else drawn from `generator`).

    held: (targets, masks) [F - 1, C, h, w] (`warp.WarpTargets`): after each of the first `hold`
    steps, where a mask is 1 the frame is its target noised to the next timestep with the frame's
    own starting noise (the target itself after the last step)."""
    sched = _scheduler(model.cfg, steps)
    f = len(conds)
    x, timesteps = _start(sched, (f - 1, *first.shape), generator, strength, None, model.cfg.flow_noise, noise)
    dev = device_of(model)
    x, first, c = x.to(dev), first.to(dev), conds.to(dev)
    with clip_frames(model, f):
        for k, t in enumerate(timesteps):
            # 1. the clean first frame enters at timestep 0, the others at t; 2. predict the
            # clip's noise; 3. step only the frames being generated.
            tt = _timesteps(t, f, dev)
            tt[0] = 0
            out = model(torch.cat([first[None], x]), tt, c)[1:].float()
            x = _hold(sched, _step(sched, out, t, x), k, timesteps, held, hold, noise, model.cfg)
    return x.cpu()
