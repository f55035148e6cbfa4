"""Our additions to the paper's Skyeyes: four steps the paper does not have, none of them learned,
run only by the methods that name them (`skyeyes-geo` and its ablation `skyeyes-geo-no-vcm`,
never `skyeyes`). Each is a component built from its own config, says the scene assumption it
makes, and where it can, checks it and steps aside:

| component | when | assumption | checked |
|---|---|---|---|
| `CarriedNoise` (noise) | the starting noise | a still scene whose prior renders move as the picture does | the flow's forward-backward test, per pixel |
| `PriorAnchor` (anchor) | after sampling | the prior's render is right about a frame's coarse layout | no |
| `StreetFromOneView` (street) | after the anchor | the street under the cameras is one level plane | per scene: a plane through the prior's Gaussians |
| `SkyFromOneFit` (sky) | last | the sky is a smooth function of the direction | per sequence: the fit's residual |

`AdditionsConfig` is the family's config (`DiffusionConfig`) with one nested config per
component (`--set anchor.mix=0.6`); `Additions.of(config)` builds the components a config turns
on (a config without these fields, the paper's, turns on none).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from ..config import DiffusionConfig
from .anchor import PriorAnchor, PriorAnchorConfig
from .noise import CarriedNoise, CarriedNoiseConfig
from .sky import SkyConfig, SkyFromOneFit
from .street import StreetConfig, StreetFromOneView
from .view import SequenceView

__all__ = ["AdditionsConfig", "Additions", "SequenceView", "CarriedNoise", "CarriedNoiseConfig", "PriorAnchor",
           "PriorAnchorConfig", "StreetFromOneView", "StreetConfig", "SkyFromOneFit", "SkyConfig"]


@dataclass(frozen=True)
class AdditionsConfig(DiffusionConfig):
    """A run of the diffusion family with our additions (each off at its default)."""

    noise: CarriedNoiseConfig = field(default_factory=CarriedNoiseConfig)
    anchor: PriorAnchorConfig = field(default_factory=PriorAnchorConfig)
    street: StreetConfig = field(default_factory=StreetConfig)
    sky: SkyConfig = field(default_factory=SkyConfig)


#: The steps after sampling, in the order they run: (config field, component).
POST_STEPS = (("anchor", PriorAnchor), ("street", StreetFromOneView), ("sky", SkyFromOneFit))


@dataclass
class Additions:
    """The components a run's config turns on: `noise` (the starting noise; None: every frame
    its own draw) and `post` (steps after decoding, in order)."""

    noise: CarriedNoise | None = None
    post: list = dataclasses.field(default_factory=list)

    @classmethod
    def of(cls, config) -> "Additions":
        if not isinstance(config, AdditionsConfig):
            return cls()
        steps = [make(getattr(config, name)) for name, make in ((n, c.make) for n, c in POST_STEPS)]
        return cls(CarriedNoise.make(config.noise), [s for s in steps if s is not None])

    @property
    def components(self) -> list:
        return ([self.noise] if self.noise is not None else []) + list(self.post)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.components]

    @property
    def needs_gaussians(self) -> bool:
        """Whether a component reads the prior's depth or Gaussians (a Gaussian prior's fitted scenes)."""
        return any(c.needs_gaussians for c in self.components)
