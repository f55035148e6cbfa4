"""Geospecific View Generation baseline (Skyeyes Tab. 1-2, "GVG"; Xu & Qin, ECCV 2024): a
diffusion model that generates each ground view from what the overhead views' reconstructed
geometry projects into it.

GVG (arXiv 2407.08061; its GeoContext-v1 data card) reconstructs the scene's geometry from
multi-view satellite images, refines the buildings, and renders into the ground panorama the
satellite texture projected through that geometry together with geometry-derived layout (its
data pairs each ground view with the projected texture, depth and semantics); Skyeyes describes
it as conditioning on "both texture and high-frequency layout" (Sec. 2). A diffusion model
fine-tuned from Stable Diffusion generates the ground view from these conditions, one view at a
time, with a "geospecific prior" that biases it towards imagery of the same place.

Here, per ground frame, the condition is [colour, depth, mask] concatenated to the denoiser's
input (`CoreConfig.cond_extra = 2`):

* colour: the aerial texture projected into the ground camera through the reconstructed geometry,
  i.e. the fused MVS cloud's render (the part `mvs` is made of: dense stereo of the lane's aerial views,
  each point a disc, `reference.common.geometry.splat`) in the aerial views' own colours, over
  the lane's own background colours where no disc projects (`train_lanes=0`: nothing learned
  from other lanes, as a prior should be);
* depth: the discs' planar depth, as inverse depth `depth_ref_m / depth` in [0, 1] (1 at
  `depth_ref_m` or nearer, 0 at infinity and where nothing projects);
* mask: 1 where the aerial views' geometry covers the pixel (coverage > 0.5), 0 elsewhere.

Frame by frame, no cross-frame attention (no VCM). Architecture, objective and schedule are the
diffusion family's presets' (`reference.common.diffusion.presets`, Skyeyes'): the residual from the colour channel is diffused, as
Skyeyes diffuses its residual from the SuGaR prior, since the projected texture is an estimate
of the frame where the mask is 1. Stereo preset per size: `smoke` at smoke, the `fast` start of
the splatting methods at small, `paper` at paper (`prior_preset`).

What differs from GVG, and why: oblique aerial views at 52 m, not satellite images (the task);
perspective frames, not panoramas (the protocol); the MVS cloud, not a refined building mesh
(no building refinement); no semantic channel (the method sees aerial pixels, not labels); no
separate high-frequency channel (the projected colour carries what the aerial views resolved);
no geospecific prior (train and test towns differ; nothing of the test place but its aerial
views may be used); a small UNet trained from scratch with the condition concatenated on the CPU
presets, where GVG fine-tunes SD (with `--pretrained` the SD1.5 UNet's conv_in is widened for
the condition instead, `core.widen_conv_in`).

The method is the diffusion pipeline (`reference.common.diffusion.pipeline`) with this
condition: the fused MVS cloud (`reference.common.mvs_cloud.MVSCloud(geometry=True)`, the
part the `mvs` row is made of) as the prior, its renders encoded by `condition_channels`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import partial

import numpy as np

from reference.common.diffusion.conditions import PriorRenders
from reference.common.diffusion.config import WHOLE_UNET_LR, DiffusionConfig
from reference.common.diffusion.pipeline import DiffusionMethod
from reference.common.diffusion.presets import baseline_presets
from reference.common.mvs_cloud import MVSCloud
from reference.method import Method

def condition_channels(raw: np.ndarray, depth_ref_m: float) -> np.ndarray:
    """A geometry render of the fused MVS cloud [H, W, 5] (colour, depth m, alpha:
    `reference.common.mvs_cloud.geometry_render`) -> the condition [H, W, 5] in [0, 1]:
    colour, inverse depth min(depth_ref_m / depth, 1) where the mask is 1 (0 elsewhere), and the
    mask alpha > 0.5."""
    assert raw.ndim == 3 and raw.shape[-1] == 5, raw.shape  # r, g, b, depth_m, alpha
    depth, alpha = raw[..., 3], raw[..., 4]
    mask = (alpha > 0.5) & (depth > 0)
    inv = np.where(mask, np.minimum(depth_ref_m / np.where(mask, depth, 1.0), 1.0), 0.0)
    return np.concatenate([raw[..., :3], inv[..., None], mask[..., None]], -1).astype(np.float32)


@dataclass(frozen=True)
class GVGConfig(DiffusionConfig):
    """The diffusion family's config (`prior_preset`: the `mvs` stereo preset) plus the depth
    encoding."""

    depth_ref_m: float = 2.0  # inverse depth is 1 at this depth (the ground cameras' height) or nearer


def gvg_config(base: DiffusionConfig, mvs_preset: str) -> GVGConfig:
    """The gvg preset made from a preset of the family (Skyeyes'): its core with the condition
    concatenated (also at `paper`, where Skyeyes has a ControlNet branch) with the depth and mask
    channels, the `mvs` geometry of `mvs_preset` as the prior, frame by frame."""
    fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(DiffusionConfig)}
    fields.update(core=dataclasses.replace(base.core, conditioning="concat", cond_extra=2), prior_method=MVSCloud.name, prior_preset=mvs_preset,
                  condition="prior", vcm=False,
                  pretrained_acm_lr=WHOLE_UNET_LR)
    return GVGConfig(**fields)


#: NOTE: the stereo presets as the splatting methods start from them (gaussians3d's `mvs_preset`):
#: `fast` at small halves `small`'s stereo cost for the same depth accuracy (bench/mvs.py).
PRESETS = baseline_presets(lambda k, v: gvg_config(v, {"smoke": "smoke", "small": "fast", "paper": "paper"}[k]))


class GVG(DiffusionMethod):
    name = "gvg"
    kind = "baseline"
    presets = PRESETS
    pretrained_conditioning = "concat"

    def __init__(self, config: GVGConfig, workdir, **kw):
        super().__init__(config, workdir, **kw)
        if self.config.prior_method != MVSCloud.name:
            raise ValueError(f"gvg prior_method {self.config.prior_method!r}: its geometry is the fused MVS cloud's "
                             f"({MVSCloud.name!r})")
        if self.config.core.cond_extra != 2:
            raise ValueError("gvg: the condition has 2 extra channels (depth, mask): core.cond_extra=2")

    def make_prior(self) -> Method:
        """The fused MVS cloud (`MVSCloud`) of `prior_preset` rendering its geometry, with no
        appearance learned on other lanes (a prior sees its own lane only)."""
        config, _ = MVSCloud.configure(self.config.prior_preset, values={"train_lanes": 0, "device": self.device})
        return MVSCloud(config, self.workdir / "prior", seed=self.seed, progress=self.progress, geometry=True)

    def condition_label(self) -> str:
        return "condition: the mvs cloud's projected aerial texture, inverse depth and coverage mask"

    def make_condition(self) -> PriorRenders:
        """The prior's geometry renders as condition channels (colour, inverse depth, mask)."""
        return PriorRenders(lambda: self.prior, partial(condition_channels, depth_ref_m=self.config.depth_ref_m))
