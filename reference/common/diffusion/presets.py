"""The diffusion family's presets: Skyeyes' formulation and training budget at each size. Every
member trains with this budget (ACM steps, rate schedule, precision, batch, crops; issue 36), so
the board compares like with like: Skyeyes takes the presets as they are, the frame-by-frame
members derive theirs in their own modules (`frame_by_frame`, then their own changes).
"""

from __future__ import annotations

from .config import CoreConfig, DiffusionConfig, frame_by_frame

PRESETS: dict[str, DiffusionConfig] = {
    # CI: whole `reproduce --preset smoke` (SynthTown smoke, 48x48) in a few minutes. CPU
    # formulation (docs/skyeyes.md, "What was tried"): the prior concatenated to the UNet's
    # input, the residual from the prior diffused, EMA weights, min-SNR weighting.
    "smoke": DiffusionConfig(
        core=CoreConfig(resolution=48, patch=1, channels=(32, 64, 64), attention=(False, False, True),
                        head_dim=32, embed_dim=64, conditioning="concat", residual=True, residual_scale=2.0),
        prior_preset="smoke", base_steps=0, acm_steps=600, acm_batch=8, acm_lr=1e-3,
        vcm_steps=60, vcm_batch=1, sample_steps=10, ema_decay=0.995, snr_gamma=5.0),
    # CPU default (SynthTown small, 128x128 folded to 64x64x12: at 128 the fold is what keeps
    # a step near the 64x64 cost).
    # NOTE: measured here (2 shared cores, load ~4): a training step at batch 12 cost 8.0 CPU-s
    # on whole 64x64x12 frames and 0.66 CPU-s on 32x32 crops, so `small` trains on crops, with
    # coordinate channels: without them its whole-frame samples were a collage of crops.
    # NOTE: ACM steps by measurement (docs/skyeyes.md, "What was tried"; load ~2, 0.276 s/step
    # in fp32): held-out FID 295 / 242 / 220 / 201 at 3000 / 6000 / 9000 / 12000 constant-rate
    # steps; decaying the rate over the last 3000 of 12000 steps bettered every metric by about
    # what 1000 more constant steps give; the VCM changed nothing measurable at 300 steps and
    # lowered the warp error at the paper's 3000. bf16 autocast (this machine's CPU has AMX)
    # makes a step 0.28 -> 0.20 s and sampling 2x faster, which pays for both: 72 min from a clean
    # clone with an empty cache, set-up and scoring included (docs/skyeyes.md, Results). On a CPU
    # without native bf16, `--set mixed_precision=no` is faster.
    "small": DiffusionConfig(
        core=CoreConfig(resolution=128, patch=2, channels=(32, 64, 128), attention=(False, False, True),
                        head_dim=32, embed_dim=64, conditioning="concat", residual=True, residual_scale=2.0,
                        coords=True),
        prior_preset="small", base_steps=0, acm_steps=12000, acm_anneal=3000, acm_batch=16, acm_lr=1e-3,
        train_crop=32, vcm_steps=3000, vcm_batch=1, sample_steps=10, ckpt_every=100, ema_decay=0.995,
        snr_gamma=5.0, mixed_precision="bf16", vcm_noise=1.0, vcm_noise_flow=True, vcm_anchor=3.0,
        vcm_anchor_mix=0.5, vcm_anchor_tiles=4, vcm_street=0.8, vcm_sky=1.0),
    # NOTE: the street from one view (`vcm_street`, 0.8 of the way) and the sky from one fit of the
    # sequence's (`vcm_sky`), after the anchor. On all 8 synthtown@3 scenes (docs/skyeyes.md, "The
    # sky from one fit"), applied to the same sampled frames: warp error 0.0527 -> 0.0431 (no-VCM:
    # 0.0928, -54%, the interval's end -51%), FID 190 -> 167, LPIPS 0.3746 -> 0.3699 (no-VCM
    # 0.3728), SSIM and PSNR better; FVD 593 -> 616 credibly worse (no-VCM: 739). The street alone
    # (anchor 0.6) cut the warp error to 0.0462 but cost LPIPS 0.002; the sky pays that back: the
    # generated skies are washes and ghosts of buildings, the truth's a smooth gradient.
    # NOTE: the prior anchor (`vcm_anchor`): after sampling, each frame's 3-px low-pass moves half
    # way to its prior render's, the render's colours first mapped to the frames on a 4x4 grid.
    # On all 8 synthtown@3 scenes in one cache (docs/skyeyes.md, "The prior anchor"): warp error
    # 0.0652 -> 0.0527 on top of carried noise (no-VCM: 0.0928), PSNR +0.64, LPIPS 0.0023 better,
    # FID/KID/FVD ties with it. At mix 0.7 the warp error was 0.0493, but FID credibly worse than
    # no-VCM's by 6.
    # NOTE: the paper's VCM wiring, every frame's starting noise carried along the flow between the
    # prior's renders (`vcm_noise_flow`): measured here against no-VCM in one cache, the warp error
    # 0.0652 against 0.0928 and FVD 582 against 739 (both credibly better), FID a tie, LPIPS 0.004
    # credibly worse (docs/skyeyes.md, "The VCM"); the paper's wiring with independent noise
    # lowered the warp error by 0.0005. `--set clip_frames=2 --set vcm_local=5 --set vcm_warp=9` (warped
    # sampling) cut the warp error by 35% here (0.0605 against no-VCM's 0.0928) and bettered FVD
    # (613 against 739), but was credibly worse on FID (+16) and LPIPS (+0.012) and rendered 12x
    # slower (3902 s against 335 s): docs/skyeyes.md, "The VCM: what makes frames agree".
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
#: twice the batch. NOTE: on one H200 a `small` ACM step cost 0.051 s at batch 16 (launch
#: overhead: the model is far too small to fill a GPU; ../MEASURED.md, b99d601), so steps, not
#: batch, set a GPU run's time: 12000 steps alone are ~10 min there. Measured on this CPU at
#: `smoke` (docs/gpu.md, against the preset's 600 steps at batch 8, FID 324.5): 300 steps at
#: batch 16 FID 344.9 (LPIPS +0.023 worse), 150 at batch 32 FID 404.2, the same with the rates
#: doubled FID 404.8, each credibly worse: fewer steps cost quality even at equal frames seen,
#: so the trade is the mildest one. Whether `small` at this shape is credibly worse than its
#: CPU row is for a GPU run to show (docs/gpu.md); the CPU presets stay as they are.
GPU_TRAINING = {"small": dict(acm_steps=6000, acm_anneal=1500, acm_batch=32, vcm_steps=1500, vcm_batch=2)}


def baseline_presets(derive) -> dict[str, DiffusionConfig]:
    """`{preset: derive(preset, the family's preset without the VCM)}`: what a frame-by-frame
    member's presets are made of, in its own module (`frame_by_frame`: the VCM off, its settings
    at their defaults; the training budget kept)."""
    return {k: derive(k, frame_by_frame(v)) for k, v in PRESETS.items()}
