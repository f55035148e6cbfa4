"""Run by test_skyeyes_parallel.py (next to this file) under `accelerate launch` (CPU processes,
gloo), or directly (one process): Skyeyes' real train-split stages (ACM, then the VCM on clips)
on the tiny hand-made dataset with the test-only stand-in prior; the main process writes the
trained ACM and VCM weights and the training summary to OUT.

    python tests/reference/methods/_skyeyes_ddp_runner.py OUT DATA WORKDIR VCM_BATCH
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # builders, under accelerate launch

from builders.skyeyes import SIZE, StandInPrior  # noqa: E402
from reference.methods.skyeyes import PRESETS, Skyeyes  # noqa: E402
from skyeyes_bench.data.layout import open_dataset  # noqa: E402

CFG = dataclasses.replace(
    PRESETS["smoke"],
    core=dataclasses.replace(PRESETS["smoke"].core, resolution=SIZE, channels=(16, 32), attention=(False, True),
                             head_dim=8, embed_dim=16, norm_groups=4),
    acm_steps=3, acm_batch=4, vcm_steps=3, clip_frames=3, ckpt_every=2, device="cpu", threads=1,
    mixed_precision="no")


def run(out: Path, data: Path, workdir: Path, vcm_batch: int) -> None:
    torch.set_num_threads(1)
    m = Skyeyes(dataclasses.replace(CFG, vcm_batch=vcm_batch), workdir, prior_method=StandInPrior(workdir / "prior"),
                progress=False)
    m.fit_train(open_dataset(data))
    from accelerate import PartialState

    state = PartialState()
    if state.is_main_process:
        torch.save({"acm": m.acm.state_dict(), "vcm": m.vcm.state_dict(), "training": m.training}, out)
    state.wait_for_everyone()


if __name__ == "__main__":
    run(Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4]))
