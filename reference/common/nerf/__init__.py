"""A compact Instant-NGP (Müller et al. 2022) in pure torch, used by the `nerf` method.

- `encoding`: the multiresolution hash encoding (`HashEncoding`, `HashGridConfig`).
- `render`: the scene box, the far field's contraction, ray sampling, volume rendering weights.
- `field`: the density and colour MLPs (`NeRFField`) and the occupancy grid (`OccupancyGrid`).
- `train`: ray marching through the grid, the training loop, rendering a camera.
- `bake`: the fitted field on a dense grid over the box, and the ground renderer that marches
  through it (`bake_field`, `BakedField`, `render_baked_camera`).
"""

from reference.common.nerf.bake import BakedField, bake_field, render_baked_camera, render_baked_rays
from reference.common.nerf.encoding import HashEncoding, HashGridConfig, level_resolutions
from reference.common.nerf.field import FieldConfig, NeRFField, OccupancyGrid
from reference.common.nerf.render import SceneBox, composite, contract, render_weights, sample_intervals
from reference.common.nerf.train import Model, NeRFConfig, camera_rays, pretrain_density, render_camera, train

__all__ = ["BakedField", "FieldConfig", "HashEncoding", "HashGridConfig", "Model", "NeRFConfig", "NeRFField",
           "OccupancyGrid", "SceneBox", "bake_field", "camera_rays", "composite", "contract", "level_resolutions",
           "pretrain_density", "render_baked_camera", "render_baked_rays", "render_camera", "render_weights",
           "sample_intervals", "train"]
