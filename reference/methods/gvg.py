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
  i.e. the `mvs` method's render of its fused cloud (dense stereo of the lane's aerial views,
  each point a disc, `reference.common.geometry.splat`) in the aerial views' own colours, over
  the lane's own background colours where no disc projects (`train_lanes=0`: nothing learned
  from other lanes, as a prior should be);
* depth: the discs' planar depth, as inverse depth `depth_ref_m / depth` in [0, 1] (1 at
  `depth_ref_m` or nearer, 0 at infinity and where nothing projects);
* mask: 1 where the aerial views' geometry covers the pixel (coverage > 0.5), 0 elsewhere.

Frame by frame, no cross-frame attention (no VCM). Architecture, objective and schedule are the
Skyeyes CPU presets' (`skyeyes.PRESETS`): the residual from the colour channel is diffused, as
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
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from reference.common.geometry import splat
from reference.method import Method
from skyeyes_bench.data.layout import Dataset, Scene, Sequence

from .mvs import MVS
from .skyeyes import WHOLE_UNET_LR, SkyeyesConfig, SkyeyesNoVCM, baseline_presets

#: Channels of a raw geometry render (`geometry_render`) and of a condition (`condition_channels`).
RAW_CHANNELS = ("r", "g", "b", "depth_m", "alpha")
CONDITION_CHANNELS = ("r", "g", "b", "inverse_depth", "mask")


def geometry_render(params: dict, cam, background: np.ndarray, *, opacity: float, near: float,
                    device="cpu", colour_map=None) -> np.ndarray:
    """The fused cloud's surfels (`splat.surfels`) seen from `cam`: float32 [H, W, 5] = colour
    over `background` [H, W, 3] (after `colour_map`, if given), planar depth (m; 0 where nothing
    projects) and coverage alpha in [0, 1]."""
    out = splat.render_surfels(params, cam, opacity=opacity, near=near, device=device)
    colour = out["colour"] if colour_map is None else colour_map(out["colour"])
    rgb = splat.over(colour, out["alpha"], background)
    return np.concatenate([rgb, out["depth"][..., None], out["alpha"][..., None]], -1).astype(np.float32)


def condition_channels(raw: np.ndarray, depth_ref_m: float) -> np.ndarray:
    """A raw render [H, W, 5] (colour, depth m, alpha) -> the condition [H, W, 5] in [0, 1]:
    colour, inverse depth min(depth_ref_m / depth, 1) where the mask is 1 (0 elsewhere), and the
    mask alpha > 0.5."""
    assert raw.ndim == 3 and raw.shape[-1] == len(RAW_CHANNELS), raw.shape
    depth, alpha = raw[..., 3], raw[..., 4]
    mask = (alpha > 0.5) & (depth > 0)
    inv = np.where(mask, np.minimum(depth_ref_m / np.where(mask, depth, 1.0), 1.0), 0.0)
    return np.concatenate([raw[..., :3], inv[..., None], mask[..., None]], -1).astype(np.float32)


class MVSGeometry(MVS):
    """The `mvs` method rendering, per ground frame, its colour with the depth and coverage of its
    discs (`geometry_render`): gvg's prior. Its renders are cached by `render_priors` under
    their own name."""

    name = "mvs-geometry"

    def render_sequence(self, scene: Scene, sequence: Sequence) -> Iterator[np.ndarray]:
        cfg = self.config
        self.use_threads()
        params, ground = self._splat(scene)
        bgs = self._backgrounds(scene, ground)
        for frame in sequence:
            cam = frame.camera()
            yield geometry_render(params, cam, bgs.image(cam), opacity=cfg.opacity, near=cfg.render_near_m,
                                  device=self.device, colour_map=self.colour_map)


@dataclass(frozen=True)
class GVGConfig(SkyeyesConfig):
    """Skyeyes' config (`prior_preset`: the `mvs` stereo preset) plus the depth encoding."""

    depth_ref_m: float = 2.0  # inverse depth is 1 at this depth (the ground cameras' height) or nearer


def gvg_config(base: SkyeyesConfig, mvs_preset: str) -> GVGConfig:
    """The gvg preset made from a Skyeyes preset: its core with the condition concatenated (also
    at `paper`, where Skyeyes has a ControlNet branch) with the depth and mask channels, the
    `mvs` geometry of `mvs_preset` as the prior, frame by frame."""
    fields = {f.name: getattr(base, f.name) for f in dataclasses.fields(SkyeyesConfig)}
    fields.update(core=dataclasses.replace(base.core, conditioning="concat", cond_extra=2), prior_method="mvs", prior_preset=mvs_preset,
                  condition="prior", vcm=False,
                  pretrained_acm_lr=WHOLE_UNET_LR)
    return GVGConfig(**fields)


#: NOTE: the stereo presets as the splatting methods start from them (gaussians3d's `mvs_preset`):
#: `fast` at small halves `small`'s stereo cost for the same depth accuracy (bench/mvs.py).
PRESETS = baseline_presets(lambda k, v: gvg_config(v, {"smoke": "smoke", "small": "fast", "paper": "paper"}[k]))


class GVG(SkyeyesNoVCM):
    name = "gvg"
    presets = PRESETS
    pretrained_conditioning = "concat"

    def __init__(self, config: GVGConfig, workdir, **kw):
        super().__init__(config, workdir, **kw)
        if self.config.prior_method != "mvs":
            raise ValueError(f"gvg prior_method {self.config.prior_method!r}: its geometry comes from 'mvs'")
        if self.config.core.cond_extra != 2:
            raise ValueError("gvg: the condition has 2 extra channels (depth, mask): core.cond_extra=2")

    def _make_prior(self) -> Method:
        return MVSGeometry.from_preset(self.config.prior_preset, self.workdir / "prior", seed=self.seed,
                                       progress=self.progress, train_lanes=0, device=self.device)

    def _conditions(self, dataset: Dataset | None, scenes: list[Scene]) -> dict[str, np.ndarray]:
        raw = super()._conditions(dataset, scenes)
        return {k: condition_channels(v, self.config.depth_ref_m) for k, v in raw.items()}
