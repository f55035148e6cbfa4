"""Training: the denoising objective (epsilon or v) for single frames and first-frame-conditioned clips, and a
short resumable loop with atomic checkpoints.

Determinism: every step draws its batch and noise from a generator seeded by (seed, step), so
a run stopped after k steps and resumed from its checkpoint performs exactly the steps an
uninterrupted run would (the optimizer state is checkpointed with the weights).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Callable

import torch

from skyeyes_bench import outputfiles

from .core import ControlledUNet, device_of

log = logging.getLogger(__name__)
#: a log line every this fraction of a stage's steps (logs stay readable; bars are for terminals)
LOG_EVERY = 0.1


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
    if kind == "flow":
        return scheduler.velocity(x0, noise)
    raise ValueError(f"prediction type {kind!r}: expected 'epsilon', 'v_prediction' or 'flow'")


def draw_timesteps(scheduler, b: int, g: torch.Generator) -> torch.Tensor:
    """b training timesteps from `g`: uniform over 0..T-1 (DDPM), over 1..T for the flow (its
    t = 0 is the clean sample, t = T the pure start)."""
    n = scheduler.config.num_train_timesteps
    lo = 1 if scheduler.config.prediction_type == "flow" else 0
    return torch.randint(lo, n + lo, (b,), generator=g, device=g.device)


def loss_weight(scheduler, t: torch.Tensor, snr_gamma: float | None) -> torch.Tensor:
    """Per-sample loss weights [B]: 1, or min-SNR-gamma (Hang et al. 2023, "Efficient Diffusion
    Training via Min-SNR Weighting Strategy"): min(SNR_t, gamma) / SNR_t for an epsilon target and
    min(SNR_t, gamma) / (SNR_t + 1) for a v target, SNR_t = ab_t / (1 - ab_t)."""
    if not snr_gamma or scheduler.config.prediction_type == "flow":
        # the flow's velocity loss is unweighted (rectified flow; SD3's uniform-time variant)
        return torch.ones(t.shape, dtype=torch.float32, device=t.device)
    ab = scheduler.alphas_cumprod.to(torch.float64)[t]
    snr = ab / (1.0 - ab)
    clipped = torch.clamp(snr, max=snr_gamma)
    w = clipped / (snr + 1.0) if scheduler.config.prediction_type == "v_prediction" else clipped / snr
    return w.float()


def _share(n: int, part: tuple[int, int]) -> tuple[slice, float | None]:
    """The rows of a global batch of n that process `rank` of `world` takes, and how its loss
    becomes its share of the global mean.

    Where `world` divides n every process takes n / world contiguous rows and its loss is their
    mean (None): data-parallel training averages the processes' gradients, so that is the mean
    over all n rows (and one process computes exactly what it always did). Otherwise each takes
    ceil(n / world) rows (the last ones fewer, or none: 2 clips over 4 processes) and its loss
    is the *sum* over them times world / n, which the average over processes turns into the same
    global mean. A process left without rows computes one row at weight 0, so it still joins the
    gradient all-reduce; the result equals one process's at the whole batch.
    """
    rank, world = part
    if n % world == 0:
        k = n // world
        return slice(rank * k, (rank + 1) * k), None
    k = -(-n // world)
    lo, hi = min(rank * k, n), min((rank + 1) * k, n)
    if lo == hi:
        return slice(0, 1), 0.0
    return slice(lo, hi), world / n


def _share_loss(per_row: torch.Tensor, scale: float | None) -> torch.Tensor:
    """This process's loss from its rows' losses [b, ...] (`_share`)."""
    return per_row.mean() if scale is None else per_row.reshape(len(per_row), -1).mean(1).sum() * scale


def denoise_loss(model, scheduler, x0: torch.Tensor, cond: torch.Tensor | None,
                 g: torch.Generator, *, part: tuple[int, int] = (0, 1),
                 snr_gamma: float | None = None, text: torch.Tensor | None = None) -> torch.Tensor:
    """Single-frame DDPM loss: E w_t ||target - f_theta(x_t, t, c)||^2 (target: `target`,
    w_t: `loss_weight`).

    x0 [B, C, h, w] clean model-space images (the *global* batch); cond [B, C, h, w] or None;
    text [B] bool or None: rows given the prompt (False: the unconditional embedding, for
    classifier-free guidance; None: the prompt everywhere, and the model is called as before).
    Timesteps and noise are drawn for the whole batch from `g` on the CPU (so every device and
    every process draws the same numbers); process `rank` of `world` (`part`) then takes its
    share (`_share`), so data-parallel processes average to the one-process loss at the whole
    batch, also where `world` does not divide it.
    """
    b = x0.shape[0]
    t = draw_timesteps(scheduler, b, g)
    noise = torch.randn(x0.shape, generator=g, device=g.device)
    s, scale = _share(b, part)
    x0, noise, t = x0[s], noise[s], t[s]
    cond = cond[s] if cond is not None else None
    x_t = scheduler.add_noise(x0, noise, t)
    want = target(scheduler, x0, noise, t)
    w = loss_weight(scheduler, t, snr_gamma)
    dev = device_of(model)
    extra = {} if text is None else {"text": text[s].to(dev)}
    pred = model(x_t.to(dev), t.to(dev), cond.to(dev) if cond is not None else None, **extra)
    err = ((pred.float() - want.to(dev)) ** 2).flatten(1).mean(1)  # [b]
    return _share_loss(err * w.to(dev), scale)


def clip_denoise_loss(model, scheduler, x0: torch.Tensor, cond: torch.Tensor,
                      g: torch.Generator, *, part: tuple[int, int] = (0, 1),
                      snr_gamma: float | None = None) -> torch.Tensor:
    """First-frame-conditioned clip loss (Skyeyes Eq. L_VCM).

    x0, cond [B, F, C, h, w] (the global batch, split like `denoise_loss`). Frame 1 of each clip
    enters clean (timestep 0); frames 2..F are noised at one timestep per clip; the loss covers
    frames 2..F only. The model must have VCM installed (`vcm.install_vcm`); the caller sets
    `clip_frames(model, F)`.
    """
    b, f = x0.shape[:2]
    t = draw_timesteps(scheduler, b, g)
    noise = torch.randn(x0.shape, generator=g, device=g.device)
    s, scale = _share(b, part)
    x0, noise, t, cond = x0[s], noise[s], t[s], cond[s]
    b = x0.shape[0]
    tt = t[:, None].expand(b, f).clone()  # [B, F]
    tt[:, 0] = 0
    x_t = scheduler.add_noise(x0.flatten(0, 1), noise.flatten(0, 1), tt.flatten()).view_as(x0)
    x_t[:, 0] = x0[:, 0]  # the first frame's clean latent is given, not noised
    want = target(scheduler, x0.flatten(0, 1), noise.flatten(0, 1), tt.flatten()).view_as(x0)
    dev = device_of(model)
    pred = model(x_t.flatten(0, 1).to(dev), tt.flatten().to(dev), cond.flatten(0, 1).to(dev)).view_as(x0.to(dev))
    err = ((pred[:, 1:].float() - want[:, 1:].to(dev)) ** 2).flatten(2).mean(2)  # [b, F - 1]
    return _share_loss(err * loss_weight(scheduler, t, snr_gamma).to(dev)[:, None], scale)


def save_checkpoint(path: Path, state: dict) -> None:
    """torch.save through a temporary file + rename: a kill never leaves a half checkpoint."""
    with outputfiles.atomic_path(path) as tmp:
        torch.save(state, tmp)


def load_checkpoint(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=True)


def anneal_factor(step: int, start: int, end: int) -> float:
    """Learning-rate factor of 0-based `step` under a linear decay over steps start..end - 1: 1
    before `start`, then (end - step) / (end - start), so the last step still moves (1 / n)."""
    if step < start:
        return 1.0
    return (end - step) / (end - start)


def stage_checkpoint(folder: Path, steps: int) -> Path:
    """`folder/train-<steps>.pt`: the checkpoint a stage asked for `steps` steps trains into.

    If it does not exist yet, it starts as a copy of the furthest checkpoint in `folder` that has
    done at most `steps` steps (finished shorter runs, or interrupted longer ones): with per-step
    generators and a constant learning rate, N steps resumed from k are the same computation as N
    steps from scratch (bench/skyeyes.py relies on it).
    """
    import shutil

    ckpt = folder / f"train-{steps}.pt"
    if not ckpt.is_file() and folder.is_dir():
        done = []
        for p in folder.glob("train-*.pt"):
            try:
                done.append((int(load_checkpoint(p)["step"]), p))
            except Exception:  # noqa: BLE001  (an unreadable checkpoint is just not a candidate)
                continue
        done = sorted(d for d in done if d[0] <= steps)
        if done:
            with outputfiles.atomic_path(ckpt) as tmp:
                shutil.copyfile(done[-1][1], tmp)
    return ckpt


def seed_stage(folder: Path, source: Path) -> float:
    """Start a stage that continues another one's run (a decay phase after its constant-rate
    steps): `source` copied into `folder` under its own step count, unless `folder` already
    holds a checkpoint (then `stage_checkpoint` resumes from that).

    Returns `source`'s recorded seconds: what the continuing stage, resumed from it (directly or
    through a later checkpoint of its own), counts as resumed work."""
    import shutil

    state = load_checkpoint(source)
    if not (folder.is_dir() and any(folder.glob("train-*.pt"))):
        with outputfiles.atomic_path(folder / f"train-{int(state['step'])}.pt") as tmp:
            shutil.copyfile(source, tmp)
    return float(state["seconds"])


def crops(g, size: int, *tensors):
    """The same random `size` x `size` window of each row of every tensor [B, ..., h, w] (one
    window per row, drawn from `g`; all of a row's frames share it). size 0: unchanged."""
    if not size:
        return tensors
    h, w = tensors[0].shape[-2:]
    if size > min(h, w):
        raise ValueError(f"train_crop {size} exceeds the model-space frame {h}x{w}")
    b = tensors[0].shape[0]
    oy = torch.randint(0, h - size + 1, (b,), generator=g, device=g.device).tolist()
    ox = torch.randint(0, w - size + 1, (b,), generator=g, device=g.device).tolist()
    return tuple(torch.stack([t[i, ..., y:y + size, x:x + size] for i, (y, x) in enumerate(zip(oy, ox))])
                 for t in tensors)


def _accumulate(acc, net, loss_fn, generator, seed: int, step: int, part: tuple[int, int], micro: int):
    """One step's gradient in `micro` passes: micro-batch j of process r is share r * micro + j of
    `world * micro` (the same global draw, from a fresh generator each pass), its loss divided by
    `micro`; gradients are synchronised across processes on the last pass only. Returns the
    step's loss (the passes' sum, what one pass would report)."""
    import contextlib

    rank, world = part
    total = 0.0
    for j in range(micro):
        sync = contextlib.nullcontext() if j == micro - 1 else acc.no_sync(net)
        with sync:
            loss = loss_fn(net, generator(seed, step), (rank * micro + j, world * micro)) / micro
            acc.backward(loss)
        total = total + loss.detach()
    return total


def make_accelerator(device: torch.device | str = "cpu", mixed_precision: str = "auto"):
    """The Hugging Face `Accelerator` the diffusion stages run under.

    Launched with `accelerate launch` (several processes, one per GPU or CPU process group) it
    takes its device and process group from the launcher and the stages run data-parallel;
    otherwise it is one process on `device` (resolved by `skyeyes_bench.devices`: "auto" is CUDA
    when available). `mixed_precision`: "auto" is bf16 on a CUDA device
    that supports it (fp16 otherwise), "no" on the CPU; or "no" / "fp16" / "bf16".
    """
    import os

    from accelerate import Accelerator

    from skyeyes_bench.devices import resolve_device

    device = resolve_device(str(device))
    distributed = int(os.environ.get("WORLD_SIZE", "1")) > 1  # set by `accelerate launch`
    cuda = torch.cuda.is_available()
    on = "cuda" if distributed and cuda else device
    mixed_precision = precision_for(on, mixed_precision, cuda=cuda, bf16=cuda and torch.cuda.is_bf16_supported())
    if device.type == "cuda" and device.index is not None and not distributed:
        torch.cuda.set_device(device)  # a single process on cuda:N
    if not distributed:
        # accelerate keeps one state per process and refuses another precision; a single
        # process (tests, bench/ running several methods) may build its stages at several.
        # Its device lives in the PartialState under it: left alone, a CPU stage built after a
        # CUDA one in the same process trained on CUDA (seen on an H200; docs/log/runs-2026.md).
        from accelerate.state import AcceleratorState

        AcceleratorState._reset_state(reset_partial_state=True)
    return Accelerator(cpu=device.type == "cpu", mixed_precision=mixed_precision)


def precision_for(device: torch.device | str, requested: str, *, cuda: bool, bf16: bool) -> str:
    """accelerate's mixed_precision for `requested` ("auto" | "no" | "fp16" | "bf16") on `device`."""
    if requested not in ("auto", "no", "fp16", "bf16"):
        raise ValueError(f"mixed precision {requested!r}: expected auto, no, fp16 or bf16")
    if requested != "auto":
        return requested
    if torch.device(device).type == "cuda" and cuda:
        return "bf16" if bf16 else "fp16"
    return "no"


def _ema(params: list[torch.nn.Parameter], decay: float, device: torch.device):
    """An exponential moving average of `params` (diffusers' `EMAModel`), or None for decay 0.
    On CUDA its update is one fused (foreach) op over all tensors instead of a few kernel launches
    per tensor; on the CPU the per-tensor update, whose rounding the filed rows were made with."""
    if not decay > 0:
        return None
    from diffusers.training_utils import EMAModel

    return EMAModel(params, decay=decay, foreach=torch.device(device).type == "cuda")


def _resume(ckpt: Path, model, opt, ema, device) -> tuple[int, list, float, float]:
    """Load the checkpoint `ckpt`, if there is one, into the model, the optimizer and the EMA.

    Returns (steps done, their losses, wall seconds, CPU seconds) so far: (0, [], 0.0, 0.0)
    without one.
    """
    if not ckpt.is_file():
        return 0, [], 0.0, 0.0
    state = load_checkpoint(ckpt)
    model.load_state_dict(state["model"])
    opt.load_state_dict(state["optimizer"])
    if ema is not None:
        ema.load_state_dict(state["ema"])
        # the checkpoint is read onto the CPU; the average must live with the weights
        ema.to(device=device)
    start, losses, seconds = state["step"], list(state["losses"]), float(state["seconds"])
    return start, losses, seconds, float(state.get("cpu_seconds", 0.0))


def _train_step(acc, net, opt, params, ema, loss_fn, part: tuple[int, int], *, seed: int, step: int,
                grad_clip: float, micro_batches: int) -> torch.Tensor:
    """One optimisation step at the optimizer's learning rate; returns this process's loss.

    1. batch + noise from the step's own generator; 2. loss (this process's share);
    3. gradients averaged over processes, clipped, AdamW update; 4. EMA.
    """
    opt.zero_grad(set_to_none=True)
    if micro_batches == 1:
        loss = loss_fn(net, step_generator(seed, step), part)
        acc.backward(loss)
    else:
        loss = _accumulate(acc, net, loss_fn, step_generator, seed, step, part, micro_batches)
    if grad_clip:
        acc.clip_grad_norm_(params, grad_clip)
    opt.step()
    if ema is not None:
        ema.step(params)
    return loss


def _set_lr(opt, lr: float, step: int, anneal_from: int | None, steps: int) -> None:
    """The rate of `step`: `lr`, decaying linearly from `anneal_from` (None: constant)."""
    if anneal_from is not None:
        for group in opt.param_groups:
            group["lr"] = lr * anneal_factor(step, anneal_from, steps)


class _StepLog:
    """`train_loop`'s bookkeeping of its steps: the progress bar (main process, a terminal), the
    losses read back from the device in batches (one wait, not one per step), a log line every
    LOG_EVERY of the steps, and when a checkpoint is due."""

    def __init__(self, acc, losses: list[float], *, start: int, steps: int, desc: str, ckpt_every: int,
                 t0: float, progress: bool):
        from tqdm import tqdm

        self.acc, self.losses, self.start, self.steps, self.desc = acc, losses, start, steps, desc
        self.ckpt_every, self.t0 = ckpt_every, t0
        self.bar = tqdm(range(start, steps), desc=desc, disable=None if (progress and acc.is_main_process) else True,
                        leave=False, initial=start, total=steps)
        if acc.is_main_process and start < steps:
            log.info("%s: steps %d..%d on %s (mixed precision %s, %d process(es))", desc, start, steps, acc.device,
                     acc.mixed_precision, acc.num_processes)
        self.every = max(1, round(steps * LOG_EVERY))
        self.pending: list[torch.Tensor] = []  # this process's losses not yet read back (a read waits for the device)

    def after(self, loss: torch.Tensor, done: int) -> bool:
        """Record the step that made `done` steps in all; whether a checkpoint is due."""
        self.pending.append(self.acc.reduce(loss.detach(), reduction="mean"))
        shown = not self.bar.disable
        ckpt_due = done % self.ckpt_every == 0 or done == self.steps
        if ckpt_due or shown or done % self.every == 0:
            self.flush()
            if shown:
                self.bar.set_postfix(loss=f"{self.losses[-1]:.4f}")
        if done % self.every == 0 and done < self.steps and self.acc.is_main_process:
            log.info("%s: %d/%d steps, %.3f s a step, loss %.4f", self.desc, done, self.steps,
                     (time.perf_counter() - self.t0) / (done - self.start), self.losses[-1])
        return ckpt_due

    def flush(self) -> None:
        """Read the pending losses back into `losses`."""
        if self.pending:
            self.losses.extend(torch.stack(self.pending).float().cpu().tolist())
            self.pending.clear()


def train_loop(model: ControlledUNet, params: list[torch.nn.Parameter],
               loss_fn: Callable[..., torch.Tensor], *, steps: int, lr: float,
               seed: int, ckpt: Path, ckpt_every: int = 50, grad_clip: float = 1.0,
               ema_decay: float = 0.0, accelerator=None, anneal_from: int | None = None,
               stop_after: int | None = None, progress: bool = True, desc: str = "train",
               micro_batches: int = 1, compile_mode: str = "") -> dict:
    """Run `steps` optimisation steps of `loss_fn` over `params`, resuming from `ckpt`.

    Args:
        loss_fn: (net, step generator, part) -> scalar loss. `net` is the model to call (wrapped
            for data-parallel training when launched so), `part` = (rank, world) says which
            share of the global batch this process takes (see `denoise_loss`).
        ckpt: checkpoint file; if it exists, training resumes from it. Written every
            `ckpt_every` steps and at the end (by the main process).
        ema_decay: if > 0, an exponential moving average of `params` (diffusers' `EMAModel`) is
            kept, checkpointed, and copied into the model when training ends.
        accelerator: from `make_accelerator` (default: one CPU process). The model is moved to
            its device.
        anneal_from: the learning rate is `lr` before this step and decays linearly from there,
            reaching 0 after step `steps` (the decay phase of a warmup-stable-decay schedule).
            None: constant. The rate of a step depends only on its index, so resuming is exact.
        stop_after: stop after this many steps *of this call* (simulates a killed run).
        micro_batches: each process computes its share of the global batch in this many
            micro-batches, one backward each, gradients accumulated (memory for batch: the same
            gradient up to float rounding). 1: one pass, as ever.
        compile_mode: "" steps the network eagerly; otherwise `torch.compile`'s mode for it (the
            same steps up to float rounding; the checkpoint holds the plain module's weights).

    Returns:
        {"steps": steps done in total, "losses": [per step], "seconds": wall time of this call
        plus the checkpoint's, "cpu_seconds": likewise in process CPU time, "resumed_seconds": the
        checkpoint's wall time (work this call reused, not redid), "done": bool}.
    """
    acc = accelerator or make_accelerator("cpu")
    ckpt = Path(ckpt)
    model.to(acc.device)
    opt = torch.optim.AdamW(params, lr=lr, weight_decay=0.0)
    ema = _ema(params, ema_decay, acc.device)
    start, losses, seconds, cpu = _resume(ckpt, model, opt, ema, acc.device)
    net, opt = acc.prepare(model, opt)
    if compile_mode:
        net = torch.compile(net, mode=compile_mode)
    part = (acc.process_index, acc.num_processes)
    t0, c0 = time.perf_counter(), time.process_time()

    def save(step: int) -> None:
        state = {"model": model.state_dict(), "optimizer": opt.state_dict(), "step": step,
                 "losses": losses, "seconds": seconds + time.perf_counter() - t0,
                 "cpu_seconds": cpu + time.process_time() - c0}
        if ema is not None:
            state["ema"] = ema.state_dict()
        if acc.is_main_process:
            save_checkpoint(ckpt, state)
        acc.wait_for_everyone()

    model.train()
    log_ = _StepLog(acc, losses, start=start, steps=steps, desc=desc, ckpt_every=ckpt_every, t0=t0,
                    progress=progress)
    done_now = start
    for step in log_.bar:
        _set_lr(opt, lr, step, anneal_from, steps)
        loss = _train_step(acc, net, opt, params, ema, loss_fn, part, seed=seed, step=step,
                           grad_clip=grad_clip, micro_batches=micro_batches)
        done_now = step + 1
        if log_.after(loss, done_now):
            save(done_now)
        if stop_after is not None and done_now - start >= stop_after:
            break
    log_.flush()
    wall, proc = time.perf_counter() - t0, time.process_time() - c0
    if acc.is_main_process and done_now > start:
        log.info("%s: %d steps in %.0f s (%.3f s a step)", desc, done_now - start, wall, wall / (done_now - start))
    model.eval()
    if ema is not None and done_now >= steps:
        ema.copy_to(params)  # the finished model is the average
    acc.free_memory()  # drops the references `prepare` kept (optimizer state)
    # CPU seconds (all threads of this process) are reported beside wall time: on a shared
    # machine they say what the run would take alone.
    return {"steps": done_now, "losses": losses, "seconds": seconds + wall,
            "cpu_seconds": cpu + proc, "resumed_seconds": seconds, "done": done_now >= steps}
