"""ControlNet baseline (Skyeyes Tab. 1): the Skyeyes diffusion core conditioned on the aerial
image instead of the Gaussian prior, frame by frame (no view consistency module).

Which aerial image per ground frame: the aerial view whose camera centre is nearest the ground
camera's (`reference.common.diffusion.conditions.NearestAerial`). The diffusion pipeline
(`reference.common.diffusion.pipeline`) with the condition `config.condition = "aerial"` names;
its presets are the family's budget without the VCM (`presets.baseline_presets`). The base UNet
stage is shared with Skyeyes (same cache key); only the ControlNet branch differs.
"""

from __future__ import annotations

import dataclasses

from reference.common.diffusion.pipeline import DiffusionMethod
from reference.common.diffusion.presets import baseline_presets


class ControlNetBaseline(DiffusionMethod):
    name = "controlnet"
    kind = "baseline"
    presets = baseline_presets(lambda k, v: dataclasses.replace(v, vcm=False, condition="aerial"))
