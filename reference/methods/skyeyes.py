"""Skyeyes (WACV 2025): Gaussian prior -> appearance control module -> view consistency module.

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

Inference: frame 1 from the ACM, then clips of 12 frames conditioned on the last generated
frame, autoregressively. `SkyeyesNoVCM` is the paper's ablation (ACM frame by frame).

Both are the diffusion pipeline (`reference.common.diffusion.pipeline`) with its default parts:
the prior's renders as the condition (`config.prior_method`, from the registry), no guidance;
their presets are the family's (`reference.common.diffusion.presets`: Skyeyes' formulation and
training budget), without the VCM for the ablation.
"""

from __future__ import annotations

from reference.common.diffusion.config import frame_by_frame
from reference.common.diffusion.presets import PRESETS as FAMILY_PRESETS
from reference.common.diffusion.pipeline import DiffusionMethod

PRESETS = FAMILY_PRESETS


class Skyeyes(DiffusionMethod):
    """The paper's method: the prior's renders condition the ACM; the VCM carries each clip's
    frames on from the last generated one."""

    name = "skyeyes"
    presets = PRESETS


class SkyeyesNoVCM(DiffusionMethod):
    """The paper's ablation: the appearance control module frame by frame (no VCM)."""

    name = "skyeyes-no-vcm"
    presets = {k: frame_by_frame(v) for k, v in PRESETS.items()}
