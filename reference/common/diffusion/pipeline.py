"""The diffusion family's method: one pipeline, assembled per member from small parts.

`DiffusionMethod` is a `Method` whose life cycle is the same for every member (Skyeyes, its
no-VCM ablation, controlnet, ip2p, gvg):

- `fit_train`: the condition of every train ground frame, then the stages (`stages`: base UNet,
  ACM, VCM), each trained or resumed from the stage cache;
- `fit_scenes`: the condition of every test ground frame (its part, `scene_parts`: a prior
  fitted per scene), kept per scene by the one hook, `fit_scene_model`;
- `render_sequence`: DDIM from the ACM frame by frame, or with the VCM clip by clip
  (`sample`), seeded per sequence; then the steps after sampling its config turns on (`additions`:
  none for the paper's Skyeyes).

What a member chooses, in its own module:

- its presets (the family's budget, `presets`, with its own changes) and config (`DiffusionConfig`
  or an extension of it);
- the condition part, `make_condition` (`conditions`: a prior's renders, the nearest aerial view;
  by default what `config.condition` names, with the prior part `config.prior_method` names:
  `reference.common.priors.PRIOR_PARTS`);
- the guidance part, `make_guidance` (`guidance.Unguided`, or IP2P's `ImageTextGuidance`);
- whether a VCM runs: its config (`vcm`, `clip_frames`);
- our additions (`additions.AdditionsConfig`: carried noise, prior anchor, street, sky), only
  for the members that name them (`skyeyes-geo`);
- `pretrained_conditioning`: how its condition enters a pretrained SD1.5 UNet.
"""

from __future__ import annotations

import dataclasses
import zlib
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Iterator

import numpy as np

from reference.common.priors import GAUSSIAN_PRIORS, frame_key, prior_part
from reference.method import Method
from skyeyes_bench.data.layout import Dataset, Scene, Sequence

from .additions import Additions, AdditionsConfig, SequenceView
from .conditions import NearestAerial, PriorFits, PriorRenders, SceneConditions
from .config import DiffusionConfig
from .guidance import Unguided
from .presets import GPU_TRAINING

if TYPE_CHECKING:
    import torch


#: `DiffusionConfig.compile`'s values: eager, or a torch.compile mode
COMPILE_MODES = ("", "default", "reduce-overhead", "max-autotune-no-cudagraphs")


def adapted(config: DiffusionConfig, pretrained_conditioning: str) -> DiffusionConfig:
    """`config` as it runs, after checking it: with `pretrained`, the folder's schedule and
    objective, the member's way in for the condition and the recipe's learning rate; with an
    aerial condition, the frames diffused rather than their residual from it."""
    if config.pretrained:
        # SD1.5's UNet was trained on the epsilon objective and its condition enters through
        # a ControlNet branch (the paper's ACM; the concatenating baselines widen conv_in
        # instead, `pretrained_conditioning`); its fine-tuning keeps both. Its ControlNet
        # takes pixels 8x the latent's size, so no training crops (they would not align).
        # Its noise schedule and objective are the folder's (`pretrained_schedule`), for
        # training and sampling alike, and its learning rate the recipe's (`pretrained_acm_lr`).
        from .core import pretrained_schedule

        core_cfg = dataclasses.replace(config.core, pretrained=config.pretrained, conditioning=pretrained_conditioning,
                                       residual=False, coords=False, **pretrained_schedule(config.pretrained))
        config = dataclasses.replace(config, core=core_cfg, sample_strength=1.0, train_crop=0, vcm_crop=-1,
                                     acm_lr=config.pretrained_acm_lr)
    if config.sample_strength < 1.0 and not config.core.residual:
        raise ValueError("sample_strength < 1 (an SDEdit start from the prior) needs core.residual")
    if not 0 <= config.acm_anneal < max(config.acm_steps, 1):
        raise ValueError(f"acm_anneal {config.acm_anneal}: expected 0 <= acm_anneal < acm_steps "
                         f"({config.acm_steps}); the decay follows at least one constant-rate step")
    if config.clip_frames < 1:
        raise ValueError(f"clip_frames {config.clip_frames}: expected >= 1")
    if config.vcm_snr_gamma < 0 and config.vcm_snr_gamma != -1:
        raise ValueError(f"vcm_snr_gamma {config.vcm_snr_gamma}: expected -1 (snr_gamma's), 0 (uniform) or > 0")
    if config.vcm_crop < -1:
        raise ValueError(f"vcm_crop {config.vcm_crop}: expected -1 (train_crop's), 0 (whole frames) or a crop size")
    if isinstance(config, AdditionsConfig):
        adds = Additions.of(config)
        if adds.components and config.condition != "prior":
            raise ValueError(f"{', '.join(adds.names)}: need a prior's renders as the condition (their flow, their "
                             f"colours), not condition={config.condition!r}")
        if adds.needs_gaussians and config.prior_method not in GAUSSIAN_PRIORS:
            raise ValueError(f"{', '.join(c.name for c in adds.components if c.needs_gaussians)}: need the renders of a "
                             f"Gaussian prior ({', '.join(GAUSSIAN_PRIORS)}; its depth and Gaussians find the street "
                             f"and the sky), not {config.prior_method!r}")
    if config.compile not in COMPILE_MODES:
        raise ValueError(f"compile {config.compile!r}: expected one of {', '.join(map(repr, COMPILE_MODES))} "
                         "('' is eager)")
    if config.condition == "aerial" and config.core.residual:
        # the residual from a view taken elsewhere means nothing: diffuse the frames
        config = dataclasses.replace(config, core=dataclasses.replace(config.core, residual=False),
                                     sample_strength=1.0)
    return config


def to_model(images: list[np.ndarray], resolution: int):
    """float32 [H, W, C] images -> torch [N, C, resolution, resolution] (antialiased resize)."""
    import torch

    from .core import images_to_tensor, resize

    return torch.cat([resize(images_to_tensor(im[None]), resolution) for im in images])


class DiffusionMethod(Method):
    """The diffusion family's life cycle over its parts (the module docstring says which)."""

    version = "0.1"
    #: How the condition enters a pretrained SD1.5 UNet (`--pretrained`): the paper's ACM is a
    #: ControlNet branch; the members that concatenate their condition (ip2p, gvg) widen conv_in.
    pretrained_conditioning: ClassVar[str] = "controlnet"

    def __init__(self, config: DiffusionConfig, workdir: Path, *, seed: int = 0, prior_method: Method | None = None,
                 progress: bool = True):
        super().__init__(adapted(config, self.pretrained_conditioning), workdir, seed=seed, progress=progress)
        self._prior = prior_method  # tests inject a stand-in; else built when first needed (`make_prior`)
        self.condition = self.make_condition()
        self.guidance = self.make_guidance()
        self.additions = Additions.of(self.config)  # none for a config without them (the paper's)
        self.acm = None
        self.vcm = None
        self.training: dict[str, Any] = {}  # stage -> its summary (training.json)
        self._figure_written = False

    @classmethod
    def configure(cls, preset: str, sets: list[str] | tuple = (), *, values: dict | None = None,
                  device: str | None = None, pretrained: str | None = None) -> tuple[Any, list[str]]:
        """`Method.configure`, then on a CUDA device the preset's `GPU_TRAINING` for the fields
        neither `sets` nor `values` name (they join the returned overrides, so the run's own
        record repeats it on any machine)."""
        from skyeyes_bench.devices import resolve_device

        config, applied = super().configure(preset, sets, values=values, device=device, pretrained=pretrained)
        gpu = GPU_TRAINING.get(preset, {})
        if gpu and resolve_device(config.device, what="device").type == "cuda":
            named = {s.partition("=")[0] for s in sets} | set(values or {})
            mine = {k: v for k, v in gpu.items() if k not in named}
            config = dataclasses.replace(config, **mine)
            applied = applied + [f"{k}={v}" for k, v in mine.items()]
        return config, applied

    def config_dict(self) -> dict:
        return {**dataclasses.asdict(self.config), "method": self.name}

    def components(self) -> list[str]:
        """What the run does, in order: its condition, the ACM, the VCM if any, its starting noise,
        then the steps after sampling (the board lists them with its row)."""
        c = self.config
        vcm = c.vcm and c.clip_frames > 1
        parts = [self.condition_label(), *self.guidance.labels(), "ACM" if vcm else "ACM frame by frame"]
        if vcm:
            parts.append(f"VCM ({c.clip_frames}-frame clips after the first frame)")
        parts.append(self.additions.noise.name if self.additions.noise else "pure Gaussian noise")
        return parts + [step.name for step in self.additions.post]

    def condition_label(self) -> str:
        """The condition part in words (`components`)."""
        if self.config.condition == "aerial":
            return "condition: the nearest aerial view"
        return f"condition: the {self.config.prior_method} prior's renders"

    # ---------------------------------------------------------------- the parts
    def make_condition(self) -> NearestAerial | PriorRenders:
        """The condition part: `config.condition` "aerial", the nearest aerial view; "prior", the
        renders of the prior (`prior`)."""
        if self.config.condition == "aerial":
            return NearestAerial()
        return PriorRenders(lambda: self.prior)

    def make_prior(self) -> Method:
        """The prior: the part `config.prior_method` (`priors.PRIOR_PARTS`) at `prior_preset`, on
        this device."""
        c = self.config
        return prior_part(c.prior_method, c.prior_preset, self.workdir / "prior", self.seed, self.device)

    def make_guidance(self) -> Unguided:
        """The guidance part (`guidance.Unguided`: none)."""
        return Unguided()

    @property
    def prior(self) -> Method:
        """The method whose renders are the conditions (`PriorRenders`) and whose depth and
        Gaussians the additions read, made by `make_prior` when first needed."""
        if self._prior is None:
            self._prior = self.make_prior()
        return self._prior

    # ---------------------------------------------------------------- fit
    def _conditions(self, dataset: Dataset | None, scenes: list[Scene]) -> dict[str, np.ndarray]:
        conds, cached_s = self.condition.images(dataset, scenes, progress=self.progress, jobs=self.jobs)
        self.took_from_cache(cached_s)
        return conds

    def fit_train(self, dataset: Dataset) -> None:
        from . import train
        from .stages import Stages, train_set

        c = self.config
        acc = train.make_accelerator(self.device, c.mixed_precision)
        scenes = dataset.split("train")
        frames = [(s, f) for s in scenes for f in s.ground]
        with acc.main_process_first():  # under `accelerate launch`, one process fits the priors
            conds = self._conditions(dataset, scenes)
        self.use_threads()  # the prior stage runs single-threaded; the UNet wants every core
        # 1. tensors in model space: targets and conditions, one row per train ground frame; the
        # model diffuses z0 (the frames, or their residual from the prior: `core.to_diffused`).
        data = train_set(frames, [f.image() for _, f in frames], [conds[frame_key(s, f)] for s, f in frames],
                         lambda ims: to_model(ims, c.core.resolution), c.core, acc.device)
        stages = Stages(self, acc, data)
        # 2. the base UNet (where there is one), 3. the ACM, 4. the VCM (none for 1-frame clips:
        # the ACM frame by frame).
        model, base_id = stages.base()
        acm_id = stages.acm(model, base_id, self.guidance)
        self.acm = model
        if c.vcm and c.clip_frames > 1:
            self.vcm = stages.vcm(model, acm_id, scenes)

    def scene_parts(self) -> list[SceneConditions | PriorFits]:
        """Fitted on the test scenes at once, before each scene's own fit: the condition part
        (a prior fitted per scene `jobs` at a time and rendered, `render_priors`), and where an
        addition reads the prior's depth or Gaussians, the prior's fitted scenes (cached renders
        fit none)."""
        if self.acm is None:
            raise RuntimeError(f"{self.name}: fit_train must run before fit_scene")
        if not self.additions.needs_gaussians:
            return [self.condition]
        return [self.condition, PriorFits(lambda: self.prior)]

    def fit_scene_model(self, scene: Scene, *, progress: bool) -> tuple[dict[str, np.ndarray], dict]:
        """The scene's conditions ({frame key: image}, from the condition part); the diffusion
        model is fitted on the train split."""
        return self.condition.of_scene(scene), {}

    # ---------------------------------------------------------------- render
    def render_sequence(self, scene: Scene, sequence: Sequence) -> Iterator[np.ndarray]:
        from . import core
        from .figure import write_figure

        cfg = self.config.core
        conds = self.scene_model(scene)
        priors = [conds[frame_key(scene, f)] for f in sequence.frames]
        self.use_threads()
        cc = core.encode_cond(to_model(priors, cfg.resolution), cfg, self.device)
        seed = self.sequence_seed(sequence)
        view = SequenceView(self.prior, scene, sequence, priors) if self.additions.components else None
        # 1. sample (from each frame's own noise, or what the noise addition makes of it)
        x = core.from_diffused(self._generate(cc, seed, view), cc, cfg)
        imgs = core.decode(x, cfg, self.device)  # [N, 3, res, res]
        # 2. the steps after sampling, in order (none for the paper's Skyeyes)
        for step in self.additions.post:
            imgs = step(imgs, view)
        out = []
        for f, img in zip(sequence.frames, imgs, strict=True):
            img = core.resize(img[None], f.height)[0] if (f.width == f.height) else \
                core.resize_hw(img[None], f.height, f.width)[0]
            out.append(core.tensor_to_images(img[None])[0])
        # The figure shows the first sequence rendered in this workdir. A resumed run renders
        # the sequences a killed one left undone first, so it keeps the figure already there.
        if not self._figure_written and not (self.workdir / "figure.png").is_file():
            self._figure_written = True
            write_figure(self.workdir / "figure.png", scene, sequence, priors, out, self.config.figure_frames,
                         condition=self.config.condition)
        yield from out

    def sequence_seed(self, sequence: Sequence) -> int:
        """The seed of a sequence's starting noise: from its id, so frames do not depend on
        rendering order."""
        return self.seed * 1_000_003 + zlib.crc32(sequence.id.encode())

    def _generate(self, conds, seed: int, view: SequenceView | None):
        """Model-space samples [N, C, h, w] for the conditions `conds` of a sequence's frames."""
        from . import sample

        c = self.config
        acm = self.guidance.sampling_model(self.acm)
        # every frame's own draw (`sample.frame_noise`: the same in `skyeyes` and `skyeyes-no-vcm`)
        noise = sample.frame_noise(seed, sample.sample_shape(tuple(conds.shape), acm.cfg))
        if self.additions.noise is not None:
            noise = self.additions.noise(noise, view)
        if c.vcm and self.vcm is not None:  # the config decides: a fitted VCM can be switched off
            return sample.sample_sequence(acm, self.vcm, conds, steps=c.sample_steps, seed=seed, clip=c.clip_frames,
                                          strength=c.sample_strength, noise=noise)
        return sample.sample_frames(acm, conds, steps=c.sample_steps, seed=seed, strength=c.sample_strength,
                                    noise=noise)
