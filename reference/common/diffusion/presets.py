"""The diffusion family's presets: Skyeyes' formulation and training budget at each size. Every
member trains with this budget (ACM steps, rate schedule, precision, batch, crops; issue 36), so
the board compares like with like: Skyeyes takes the presets as they are, the frame-by-frame
members derive theirs in their own modules (`frame_by_frame`, then their own changes).
"""

from __future__ import annotations

from .config import CoreConfig, DiffusionConfig, frame_by_frame

PRESETS: dict[str, DiffusionConfig] = {
    # CI: whole `reproduce --preset smoke` (SynthTown smoke, 48x48) in a few minutes. CPU
    # formulation (docs/log/skyeyes-2026-11.md, "What was tried"): the prior concatenated to the UNet's
    # input, the residual from the prior diffused, EMA weights, min-SNR weighting.
    "smoke": DiffusionConfig(
        core=CoreConfig(resolution=48, patch=1, channels=(32, 64, 64), attention=(False, False, True),
                        head_dim=32, embed_dim=64, conditioning="concat", residual=True, residual_scale=2.0),
        prior_preset="smoke", base_steps=0, acm_steps=600, acm_batch=8, acm_lr=1e-3,
        vcm_steps=60, vcm_batch=1, sample_steps=10, ema_decay=0.995, snr_gamma=5.0),
    # CPU default (SynthTown small, 128x128 folded to 64x64x12: at 128 the fold is what keeps
    # a step near the 64x64 cost). The paper's pipeline only: SuGaR prior, ACM, VCM on 12-frame
    # clips, DDIM from pure Gaussian noise (our additions: `skyeyes-geo`). Its formulation and
    # budget were chosen on the synthtown@1/@3 test split before the validation split existed
    # (docs/skyeyes.md, "Deviations from the paper"; figures: docs/log/runs-2026.md, "presets.py
    # comments"): 32x32 crops with coordinate channels (a crop's step is far cheaper than a whole
    # frame's; without the channels the samples were a collage of crops), 12000 ACM steps with
    # the rate decayed over the last 3000 (longer runs were better), bf16 autocast (faster on a
    # CPU with native bf16; without it, `--set mixed_precision=no` is faster). The VCM, chosen on the
    # validation split (docs/skyeyes.md, "Why the VCM adds so little"): uniform loss weights
    # (`vcm_snr_gamma=0`; min-SNR weights left the noisiest steps, where a frame's colours are
    # decided, nearly untrained, and the VCM with them steadied the frames a quarter as much) and
    # 6000 steps at batch 1, the clips the paper's 3k steps at batch 2 see (better than 3000 there).
    "small": DiffusionConfig(
        core=CoreConfig(resolution=128, patch=2, channels=(32, 64, 128), attention=(False, False, True),
                        head_dim=32, embed_dim=64, conditioning="concat", residual=True, residual_scale=2.0,
                        coords=True),
        prior_preset="small", base_steps=0, acm_steps=12000, acm_anneal=3000, acm_batch=16, acm_lr=1e-3,
        train_crop=32, vcm_steps=6000, vcm_batch=1, sample_steps=10, ckpt_every=100, ema_decay=0.995,
        snr_gamma=5.0, vcm_snr_gamma=0.0, mixed_precision="bf16"),
    # NOTE: Skyeyes Sec. 4.2: 512x512, ACM 30k iterations at batch 32, VCM 3k iterations at
    # batch 2 (12-frame clips). For GPU users with --pretrained (SD1.5: ControlNet branch,
    # epsilon objective; the base stage is skipped); without it, a ControlNet from scratch.
    "paper": DiffusionConfig(
        core=CoreConfig(resolution=512, patch=4, channels=(128, 256, 512, 512),
                        attention=(False, True, True, True), layers_per_block=2, head_dim=64,
                        embed_dim=768, norm_groups=32),
        prior_preset="paper", base_steps=30000, base_batch=32, acm_steps=30000, acm_batch=32,
        vcm_steps=3000, vcm_batch=2, sample_steps=50, ckpt_every=1000,
        # NOTE: SD1.5's UNet and a ControlNet branch at batch 32 of 64x64 latents keep their
        # activations in tens of GB; checkpointing them is what fits one 80 GB GPU (not yet
        # measured there: docs/gpu.md). If it still does not fit: --set micro_batches=2.
        grad_checkpointing=True),
}


#: A preset's training where the diffusion stages run on CUDA (`--device cuda`, or "auto" on a
#: machine with a GPU), unless `--set` names the field: the same frames seen, in half the steps at
#: twice the batch. A GPU step of this model costs about the same at any batch (launch overhead:
#: it is far too small to fill a GPU), so steps, not batch, set a GPU run's time; fewer steps
#: cost quality even at equal frames seen, so this is the mildest trade (docs/gpu.md, "Steps
#: against batch"; figures: docs/log/runs-2026.md, "presets.py comments"). The CPU presets stay
#: as they are.
GPU_TRAINING = {"small": dict(acm_steps=6000, acm_anneal=1500, acm_batch=32, vcm_steps=3000, vcm_batch=2)}


def baseline_presets(derive) -> dict[str, DiffusionConfig]:
    """`{preset: derive(preset, the family's preset without the VCM)}`: what a frame-by-frame
    member's presets are made of, in its own module (`frame_by_frame`: the VCM off, its settings
    at their defaults; the training budget kept)."""
    return {k: derive(k, frame_by_frame(v)) for k, v in PRESETS.items()}
