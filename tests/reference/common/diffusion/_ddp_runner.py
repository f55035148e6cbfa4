"""Run by test_diffusion_parallel.py (next to this file) under `accelerate launch` (2 CPU processes, gloo), or
directly (one process): a few training steps of a tiny concat-conditioned denoiser on a global
batch, then the main process writes the weights to OUT.

    python tests/reference/common/diffusion/_ddp_runner.py OUT BATCH CKPT_DIR
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from reference.common.diffusion import core, train

CFG = core.CoreConfig(resolution=16, channels=(16, 32), attention=(False, True), head_dim=8, embed_dim=16,
                      norm_groups=4, conditioning="concat", residual=True)


def run(out: Path, batch: int, ckpt_dir: Path, steps: int = 3) -> dict:
    torch.set_num_threads(1)
    acc = train.make_accelerator("cpu", "no")
    model = core.build_model(CFG, control=True, seed=0)
    sched = core.train_scheduler(CFG)
    g = torch.Generator().manual_seed(5)
    x0 = torch.rand(8, 3, 16, 16, generator=g) * 2 - 1
    cond = torch.rand(8, 3, 16, 16, generator=g) * 2 - 1
    z0 = core.to_diffused(x0, cond, CFG)

    def loss_fn(net, gen, part):
        idx = torch.randint(0, 8, (batch,), generator=gen)
        return train.denoise_loss(net, sched, z0[idx], cond[idx], gen, part=part, snr_gamma=5.0)

    res = train.train_loop(model, core.trainable(model), loss_fn, steps=steps, lr=1e-2, seed=0,
                           ckpt=ckpt_dir / "c.pt", ckpt_every=2, ema_decay=0.9, accelerator=acc, progress=False)
    if acc.is_main_process:
        torch.save({"model": model.state_dict(), "processes": acc.num_processes, "losses": res["losses"]}, out)
    acc.wait_for_everyone()
    return res


if __name__ == "__main__":
    run(Path(sys.argv[1]), int(sys.argv[2]), Path(sys.argv[3]))
