"""Skyeyes (WACV 2025) as the paper describes it: SuGaR prior -> appearance control module (ACM)
-> view consistency module (VCM), sampled from pure Gaussian noise. Nothing else: our additions
run under their own name (`reference.methods.skyeyes_geo`).

Stages (`reference.common.diffusion.stages`; each cached by content hash under
`<cache>/reference/diffusion/`, so `skyeyes`, `skyeyes-no-vcm` and the baselines share what they
have in common):

0. prior: the prior method (SuGaR) is fitted per lane on its *aerial* views only and rendered
   at the lane's ground poses, for train and test lanes (`reference.common.priors`).
1. base: without a pretrained Stable Diffusion, a UNet is first trained unconditionally on the
   train split's ground-truth ground frames (it stands in for the pretrained LDM).
2. ACM: a ControlNet branch made from that UNet (`ControlNetModel.from_unet`, zero
   convolutions) learns, UNet frozen, to denoise ground truth conditioned on its prior.
3. VCM: a copy of the frozen ACM gets clip self-attention (`vcm.install_vcm`); its attn1
   projections (UNet and ControlNet) are fine-tuned on 12-frame clips with first-frame
   conditioning. VCM adds no new parameters.

Inference (paper Fig. 2, supplement Sec. 2.2): frame 1 from the ACM, then clips of 12 frames
conditioned on the last generated frame, autoregressively, every frame denoised from pure
Gaussian noise. `SkyeyesNoVCM` is the paper's ablation: the same without the VCM (the ACM frame
by frame), one difference.

What the CPU presets change from the paper (the formulation, the training budget) is in
docs/skyeyes.md, "Deviations from the paper"; `PAPER_COMPONENTS` is the paper's list, which a
test holds every preset to.
"""

from __future__ import annotations

from reference.common.diffusion.config import frame_by_frame
from reference.common.diffusion.pipeline import DiffusionMethod
from reference.common.diffusion.presets import PRESETS as FAMILY_PRESETS

PRESETS = FAMILY_PRESETS

#: The paper's pipeline in the words of `DiffusionMethod.components` (Skyeyes Sec. 3, Fig. 2).
PAPER_COMPONENTS = ("condition: the sugar prior's renders", "ACM", "VCM (12-frame clips after the first frame)",
                    "pure Gaussian noise")


class Skyeyes(DiffusionMethod):
    """The paper's method: the prior's renders condition the ACM; the VCM carries each clip's
    frames on from the last generated one."""

    name = "skyeyes"
    kind = "paper"
    presets = PRESETS


class SkyeyesNoVCM(DiffusionMethod):
    """The paper's ablation: the appearance control module frame by frame (no VCM)."""

    name = "skyeyes-no-vcm"
    kind = "ablation"
    presets = {k: frame_by_frame(v) for k, v in PRESETS.items()}
