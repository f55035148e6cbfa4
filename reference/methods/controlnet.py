"""ControlNet baseline (Skyeyes Tab. 1): the Skyeyes diffusion core conditioned on the aerial
image instead of the Gaussian prior, frame by frame (no view consistency module).

Which aerial image per ground frame: the aerial view whose camera centre is nearest the ground
camera's (`reference.common.priors.nearest_aerial`). The base UNet stage is shared with Skyeyes (same cache key);
only the ControlNet branch differs.
"""

from __future__ import annotations

import dataclasses

from .skyeyes import SkyeyesNoVCM, baseline_presets


class ControlNetBaseline(SkyeyesNoVCM):
    name = "controlnet"
    presets = baseline_presets(lambda k, v: dataclasses.replace(v, vcm=False, condition="aerial"))
