"""Seconds per ACM training step and per sampled frame of a Skyeyes preset's denoiser, at each
mixed precision: what `--set mixed_precision=...` buys on this machine before a long run.

    .venv/bin/python bench/diffusion_step.py --preset small --precision no,bf16
    .venv/bin/python bench/diffusion_step.py --preset small --steps 60 --out step.json
    python3 bench/diffusion_step.py --device cuda --batch 32 --precision bf16 --compile ,reduce-overhead

The model, loss (v objective, min-SNR, EMA, crops), optimiser and sampler are the method's own
(`train.train_loop`, `sample.sample_frames`) on random tensors of the preset's shapes; nothing
is cached or read. Warm-up steps are excluded. Prints one row per precision; --out writes JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tempfile
import time
from pathlib import Path


def measure(preset: str, precision: str, *, steps: int, warmup: int, frames: int, seed: int, device: str = "cpu",
            batch: int = 0, compile_mode: str = "") -> dict:
    import torch

    from reference.common.diffusion import core, sample, train
    from reference.methods.skyeyes import PRESETS

    c = PRESETS[preset]
    c = dataclasses.replace(c, acm_batch=batch or c.acm_batch)
    cfg = c.core
    model = core.build_model(cfg, control=False, seed=seed)
    model.add_control()
    trainable = ["controlnet."] if cfg.conditioning == "controlnet" else ["unet.", "prompt"]
    params = core.trainable(model, trainable)
    sched = core.train_scheduler(cfg)
    g = torch.Generator().manual_seed(seed)
    n, res = 32, cfg.resolution
    x0 = torch.rand(n, 3, res, res, generator=g)
    cc = core.encode_cond(torch.rand(n, 3, res, res, generator=g), cfg)
    z0 = core.to_diffused(core.encode(x0, cfg), cc, cfg)

    def loss_fn(net, gen, part):
        idx = torch.randint(0, n, (c.acm_batch,), generator=gen)
        z, k = train.crops(gen, c.train_crop, z0[idx], cc[idx])
        return train.denoise_loss(net, sched, z, k, gen, part=part, snr_gamma=c.snr_gamma or None)

    acc = train.make_accelerator(device, precision)
    with tempfile.TemporaryDirectory() as d:
        kw = dict(lr=c.acm_lr, seed=seed, ckpt=Path(d) / "ckpt.pt", ckpt_every=10**9, accelerator=acc,
                  ema_decay=c.ema_decay, progress=False, compile_mode=compile_mode)
        train.train_loop(model, params, loss_fn, steps=warmup, **kw)
        r = train.train_loop(model, params, loss_fn, steps=warmup + steps, **kw)
    step_s = (r["seconds"] - r["resumed_seconds"]) / steps
    core.trainable(model, [])
    sample.sample_frames(model, cc[:1], steps=c.sample_steps, seed=seed, strength=c.sample_strength)  # warm-up
    t0 = time.perf_counter()
    sample.sample_frames(model, cc[:frames], steps=c.sample_steps, seed=seed, strength=c.sample_strength)
    frame_s = (time.perf_counter() - t0) / frames
    if acc.device.type == "cuda":
        torch.cuda.synchronize()
    return {"preset": preset, "precision": acc.mixed_precision, "device": str(acc.device), "compile": compile_mode,
            "threads": torch.get_num_threads(),
            "s_per_step": round(step_s, 4), "s_per_frame": round(frame_s, 4), "steps": steps,
            "batch": c.acm_batch, "crop": c.train_crop, "sample_steps": c.sample_steps,
            "load": [round(x, 2) for x in os.getloadavg()]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="small", help="Skyeyes preset whose denoiser is timed (default: small)")
    ap.add_argument("--precision", default="no,bf16", help="comma-separated: no, bf16, fp16 (default: no,bf16)")
    ap.add_argument("--steps", type=int, default=40, help="timed training steps (default: 40)")
    ap.add_argument("--warmup", type=int, default=5, help="untimed training steps first (default: 5)")
    ap.add_argument("--frames", type=int, default=8, help="frames sampled at once, timed (default: 8)")
    ap.add_argument("--device", default="cpu", help="torch device: cpu, cuda, cuda:N (default: cpu)")
    ap.add_argument("--batch", type=int, default=0, help="ACM batch (default: the preset's)")
    ap.add_argument("--compile", default="", help="comma-separated torch.compile modes to time, '' for eager "
                    "(e.g. ',reduce-overhead'; default: eager only)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, help="also write the rows as JSON here")
    a = ap.parse_args(argv)
    rows = [measure(a.preset, p, steps=a.steps, warmup=a.warmup, frames=a.frames, seed=a.seed, device=a.device,
                    batch=a.batch, compile_mode=m)
            for p in a.precision.split(",") for m in a.compile.split(",")]
    print(f"{'preset':8} {'device':7} {'precision':9} {'compile':16} {'batch':>5} {'s/step':>8} {'s/frame':>8}  load")
    for r in rows:
        print(f"{r['preset']:8} {r['device']:7} {r['precision']:9} {r['compile'] or 'eager':16} {r['batch']:5d} "
              f"{r['s_per_step']:8.4f} {r['s_per_frame']:8.4f}  {r['load']}")
    if a.out:
        from skyeyes_bench import outputfiles

        outputfiles.write_json(a.out, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
