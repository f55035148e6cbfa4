"""Training: the denoising objective (epsilon or v) for single frames and first-frame-conditioned clips, and a
short resumable loop with atomic checkpoints.

Determinism: every step draws its batch and noise from a generator seeded by (seed, step), so
a run stopped after k steps and resumed from its checkpoint performs exactly the steps an
uninterrupted run would (the optimizer state is checkpointed with the weights).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import torch

from skyeyes_bench import fileio

from .core import ControlledUNet


def step_generator(seed: int, step: int) -> torch.Generator:
    # NOTE: 1_000_003 is prime, so (seed, step) pairs map to distinct seeds for steps < 1e6.
    return torch.Generator().manual_seed(int(seed) * 1_000_003 + int(step))


def target(scheduler, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """What the network should output for x_t = sqrt(ab_t) x0 + sqrt(1 - ab_t) noise: the noise
    (epsilon objective) or v = sqrt(ab_t) noise - sqrt(1 - ab_t) x0 (`scheduler.config.prediction_type`)."""
    kind = scheduler.config.prediction_type
    if kind == "epsilon":
        return noise
    if kind == "v_prediction":
        return scheduler.get_velocity(x0, noise, t)
    raise ValueError(f"prediction type {kind!r}: expected 'epsilon' or 'v_prediction'")


def denoise_loss(model: ControlledUNet, scheduler, x0: torch.Tensor, cond: torch.Tensor | None,
                 g: torch.Generator) -> torch.Tensor:
    """Single-frame DDPM loss: E ||target - f_theta(x_t, t, c)||^2 (target: `target`).

    x0 [B, C, h, w] clean model-space images; cond [B, C, h, w] or None.
    """
    b = x0.shape[0]
    t = torch.randint(0, scheduler.config.num_train_timesteps, (b,), generator=g)
    noise = torch.randn(x0.shape, generator=g)
    x_t = scheduler.add_noise(x0, noise, t)
    return torch.mean((model(x_t, t, cond) - target(scheduler, x0, noise, t)) ** 2)


def clip_denoise_loss(model: ControlledUNet, scheduler, x0: torch.Tensor, cond: torch.Tensor,
                      g: torch.Generator) -> torch.Tensor:
    """First-frame-conditioned clip loss (Skyeyes Eq. L_VCM).

    x0, cond [B, F, C, h, w]. Frame 1 of each clip enters clean (timestep 0); frames 2..F are
    noised at one timestep per clip; the loss covers frames 2..F only. The model must have VCM
    installed (`vcm.install_vcm`); the caller sets `clip_frames(model, F)`.
    """
    b, f = x0.shape[:2]
    t = torch.randint(0, scheduler.config.num_train_timesteps, (b,), generator=g)
    noise = torch.randn(x0.shape, generator=g)
    tt = t[:, None].expand(b, f).clone()  # [B, F]
    tt[:, 0] = 0
    x_t = scheduler.add_noise(x0.flatten(0, 1), noise.flatten(0, 1), tt.flatten()).view_as(x0)
    x_t[:, 0] = x0[:, 0]  # the first frame's clean latent is given, not noised
    pred = model(x_t.flatten(0, 1), tt.flatten(), cond.flatten(0, 1)).view_as(x0)
    want = target(scheduler, x0.flatten(0, 1), noise.flatten(0, 1), tt.flatten()).view_as(x0)
    return torch.mean((pred[:, 1:] - want[:, 1:]) ** 2)


def save_checkpoint(path: Path, state: dict) -> None:
    """torch.save through a temporary file + rename: a kill never leaves a half checkpoint."""
    with fileio.atomic_path(path) as tmp:
        torch.save(state, tmp)


def load_checkpoint(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=True)


def train_loop(model: ControlledUNet, params: list[torch.nn.Parameter],
               loss_fn: Callable[[torch.Generator], torch.Tensor], *, steps: int, lr: float,
               seed: int, ckpt: Path, ckpt_every: int = 50, grad_clip: float = 1.0,
               stop_after: int | None = None, progress: bool = True, desc: str = "train") -> dict:
    """Run `steps` optimisation steps of `loss_fn` over `params`, resuming from `ckpt`.

    Args:
        loss_fn: step generator -> scalar loss (draws its batch and noise from the generator).
        ckpt: checkpoint file; if it exists, training resumes from it. Written every
            `ckpt_every` steps and at the end.
        stop_after: stop after this many steps *of this call* (simulates a killed run).

    Returns:
        {"steps": steps done in total, "losses": [per step], "seconds": wall time of this call
        plus the checkpoint's, "cpu_seconds": likewise in process CPU time, "resumed_seconds": the
        checkpoint's wall time (work this call reused, not redid), "done": bool}.
    """
    from tqdm import tqdm

    ckpt = Path(ckpt)
    opt = torch.optim.AdamW(params, lr=lr, weight_decay=0.0)
    start, losses, seconds, cpu = 0, [], 0.0, 0.0
    if ckpt.is_file():
        state = load_checkpoint(ckpt)
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        start, losses, seconds = state["step"], list(state["losses"]), float(state["seconds"])
        cpu = float(state.get("cpu_seconds", 0.0))
    t0, c0 = time.perf_counter(), time.process_time()

    def save(step: int) -> None:
        save_checkpoint(ckpt, {"model": model.state_dict(), "optimizer": opt.state_dict(), "step": step,
                               "losses": losses, "seconds": seconds + time.perf_counter() - t0,
                               "cpu_seconds": cpu + time.process_time() - c0})

    model.train()
    bar = tqdm(range(start, steps), desc=desc, disable=None if progress else True, leave=False, initial=start, total=steps)
    done_now = start
    for step in bar:
        # 1. batch + noise from the step's own generator; 2. loss; 3. clipped AdamW update.
        loss = loss_fn(step_generator(seed, step))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if grad_clip:
            torch.nn.utils.clip_grad_norm_(params, grad_clip)
        opt.step()
        losses.append(float(loss.detach()))
        bar.set_postfix(loss=f"{losses[-1]:.4f}")
        done_now = step + 1
        if done_now % ckpt_every == 0 or done_now == steps:
            save(done_now)
        if stop_after is not None and done_now - start >= stop_after:
            break
    model.eval()
    # CPU seconds (all threads of this process) are reported beside wall time: on a shared
    # machine they say what the run would take alone.
    return {"steps": done_now, "losses": losses, "seconds": seconds + time.perf_counter() - t0,
            "cpu_seconds": cpu + time.process_time() - c0, "resumed_seconds": seconds, "done": done_now >= steps}
