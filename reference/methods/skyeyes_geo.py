"""`skyeyes-geo`: the paper's Skyeyes plus steps of ours that steady the sequence with the
scene's geometry, none of them in the paper and none learned (`reference.common.diffusion.
additions`): each frame's starting noise carried along the prior renders' optical flow, the prior
anchor, the street from one view, and the sky from one fit, each turned on by its config's `mix`
or `share`. At `small` the validation split chose the first two (`ADDITIONS`); the street and the
sky are there to turn on (`--set street.mix=0.8`). `skyeyes-geo-no-vcm` is its matched ablation:
the same steps on the ACM frame by frame (no VCM), so the pair shows what the paper's learned VCM
adds on top of them; `skyeyes` against `skyeyes-geo` shows what the steps add to the paper's
method.
"""

from __future__ import annotations

import dataclasses

from reference.common.diffusion.additions import (AdditionsConfig, CarriedNoiseConfig, PriorAnchorConfig, SkyConfig,
                                                  StreetConfig)
from reference.common.diffusion.config import DiffusionConfig, frame_by_frame
from reference.common.diffusion.pipeline import DiffusionMethod
from reference.common.diffusion.presets import PRESETS as FAMILY_PRESETS

#: The additions at each preset. NOTE: `small`'s chosen on synthtown-v2-small-val (8 lanes of the
#: validation town) by `reproduce --split val` and bench/additions.py: the setting with the lowest
#: warp error among those no worse than none of the steps on FID, FVD and LPIPS (docs/skyeyes.md,
#: "Our additions"). `paper` takes `small`'s (never screened at 512). `smoke` runs all four, to
#: test the path.
ADDITIONS = {
    "smoke": dict(noise=CarriedNoiseConfig(share=1.0), anchor=PriorAnchorConfig(mix=0.5),
                  street=StreetConfig(mix=0.8), sky=SkyConfig(mix=1.0)),
    "small": dict(noise=CarriedNoiseConfig(share=1.0), anchor=PriorAnchorConfig(mix=0.3)),
    "paper": dict(noise=CarriedNoiseConfig(share=1.0), anchor=PriorAnchorConfig(mix=0.3)),
}


def with_additions(base: DiffusionConfig, preset: str) -> AdditionsConfig:
    """The family's preset `base` with our additions at `preset`'s settings."""
    fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(DiffusionConfig)}
    return AdditionsConfig(**fields, **ADDITIONS[preset])


PRESETS = {k: with_additions(v, k) for k, v in FAMILY_PRESETS.items()}


class SkyeyesGeo(DiffusionMethod):
    """Skyeyes plus our geometric steps (module docstring)."""

    name = "skyeyes-geo"
    kind = "beyond"
    presets = PRESETS


class SkyeyesGeoNoVCM(DiffusionMethod):
    """`skyeyes-geo` without the VCM: the same steps on the ACM frame by frame."""

    name = "skyeyes-geo-no-vcm"
    kind = "beyond"
    presets = {k: frame_by_frame(v) for k, v in PRESETS.items()}
