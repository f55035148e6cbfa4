"""Skyeyes (WACV 2025): Gaussian prior -> appearance control module -> view consistency module.

Stages (each cached by content hash under `<cache>/reference/diffusion/`, so `skyeyes`,
`skyeyes-no-vcm` and `controlnet` share what they have in common):

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
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from reference.common.priors import frame_key, nearest_aerial, render_priors
from reference.method import Method, has_field, json_sha
from skyeyes_bench import fileio
from skyeyes_bench.data.layout import Dataset, Scene, Sequence
from skyeyes_bench.paths import cache_dir

from ..common.diffusion.core import CoreConfig

# --------------------------------------------------------------------------- config


@dataclass(frozen=True)
class SkyeyesConfig:
    """Everything a run depends on. Steps are optimiser iterations; batches count frames
    (base, ACM) or 12-frame clips (VCM)."""

    core: CoreConfig = field(default_factory=CoreConfig)
    # Local Stable Diffusion 1.5 diffusers folder (`--pretrained DIR`): its UNet, VAE and text
    # encoder replace the base stage, pixel codec and null embedding. Untested offline.
    pretrained: str | None = None
    prior_method: str = "sugar"  # registry id of the prior (stage 0)
    prior_preset: str = "smoke"
    condition: str = "prior"  # "prior" (Skyeyes) | "aerial" (ControlNet baseline)
    base_steps: int = 200
    base_batch: int = 8
    # NOTE: measured on SynthTown smoke (v objective, 250 steps): AdamW at 1e-3 reached a base
    # loss 2x lower than at 2e-4 (0.086 vs 0.16 for epsilon), with no instability (grad clip 1).
    base_lr: float = 1e-3
    acm_steps: int = 200
    acm_batch: int = 8
    acm_lr: float = 1e-3
    # The ACM's learning rate with `--pretrained` (it replaces `acm_lr` there): a ControlNet branch
    # beside a frozen SD1.5 UNet follows ControlNet's recipe. NOTE: Zhang et al. 2023, ControlNet
    # training scripts (lllyasviel/ControlNet `tutorial_train.py`; diffusers' train_controlnet.py
    # example): AdamW at 1e-5. The baselines that fine-tune the whole widened UNet (ip2p, gvg) use
    # InstructPix2Pix's 1e-4 (Brooks et al. 2023, Sec. 4.1 / supplement).
    pretrained_acm_lr: float = 1e-5
    # The last `acm_anneal` of the `acm_steps` decay the learning rate linearly to 0 (the decay
    # phase of a warmup-stable-decay schedule, Hägele et al. 2024; 0: constant throughout). The
    # constant-rate steps are their own stage, so runs of any length share them in the cache.
    acm_anneal: int = 0
    vcm: bool = True
    vcm_steps: int = 40
    vcm_batch: int = 1
    vcm_lr: float = 2e-4
    # NOTE: Skyeyes Sec. 3.3: "a consecutive of 12 frames". 1: no VCM stage, the ACM frame by
    # frame in sequence order (what `vcm_warp` alone does).
    clip_frames: int = 12
    # Which frames a frame attends to in the rewired self-attention (`vcm.KEYS`: "clip", every
    # frame of its clip, the paper's; "previous", its own and the previous frame's tokens).
    vcm_keys: str = "clip"
    # Local attention of each token over the previous frame's window x window neighbourhood after
    # every resnet of the UNet's levels without self-attention (`vcm.LocalFrameAttention`; 0: none).
    vcm_local: int = 0
    # Warped sampling (`diffusion.warp`; 0: none): the clip's first frame, moved into each new
    # frame by the prior's depth and the poses, holds the pixels it reaches for this many of the
    # `sample_steps` DDIM steps. Sampling only (no stage key); needs a prior with depth (`sugar`).
    vcm_warp: int = 0
    # Train on random square crops of this size (model-space pixels; 0: whole frames), one crop
    # box per frame (ACM) or per clip (VCM). The UNet is convolutional, so it samples whole
    # frames; a crop costs (crop / size)^2 of a frame (SR3 and Palette train on crops too).
    train_crop: int = 0
    sample_steps: int = 10  # DDIM steps
    # SDEdit start (Meng et al. 2022): 1 samples from pure noise; s < 1 starts from the prior
    # noised to timestep s T (needs `core.residual`: the prior is the residual model's zero).
    sample_strength: float = 1.0
    # Exponential moving average of the trained weights (0: none); the sampler uses the average.
    ema_decay: float = 0.0
    # min-SNR-gamma loss weighting (Hang et al. 2023; 0: uniform weights).
    snr_gamma: float = 0.0
    # torch device of every stage (priors, diffusion training, sampling): "auto" is CUDA when
    # available, else the CPU. Mixed precision of the diffusion stages' training and sampling
    # (autocast; weights stay fp32): "auto" is bf16/fp16 on CUDA, none on the CPU; or no/fp16/bf16.
    # Under `accelerate launch` the diffusion stages take their devices from the launcher.
    device: str = "auto"
    mixed_precision: str = "auto"
    ckpt_every: int = 50
    # Memory for batch on a GPU (the same training up to float rounding, so neither is in the stage
    # keys): each process's share of a batch in this many micro-batches, gradients accumulated;
    # and activation checkpointing in the UNet and its ControlNet branch (recomputed in backward).
    micro_batches: int = 1
    grad_checkpointing: bool = False
    figure_frames: int = 6
    # torch threads of the diffusion stages (0: every core; OMP_NUM_THREADS wins when set).
    # NOTE: measured on SynthTown small, base stage: 2.4 s/step on 1 thread (the setting the
    # SuGaR prior leaves behind) on an otherwise idle 2-core machine.
    threads: int = 0


#: `pretrained_acm_lr` of the baselines that fine-tune a pretrained UNet whole, its conv_in
#: widened for the concatenated condition (ip2p, gvg). NOTE: InstructPix2Pix (Brooks et al.
#: 2023), its training details: learning rate 1e-4, no warm-up.
WHOLE_UNET_LR = 1e-4

PRESETS: dict[str, SkyeyesConfig] = {
    # CI: whole `reproduce --preset smoke` (SynthTown smoke, 48x48) in a few minutes. CPU
    # formulation (docs/skyeyes.md, "What was tried"): the prior concatenated to the UNet's
    # input, the residual from the prior diffused, EMA weights, min-SNR weighting.
    "smoke": SkyeyesConfig(
        core=CoreConfig(resolution=48, patch=1, channels=(32, 64, 64), attention=(False, False, True),
                        head_dim=32, embed_dim=64, conditioning="concat", residual=True, residual_scale=2.0),
        prior_preset="smoke", base_steps=0, acm_steps=600, acm_batch=8, acm_lr=1e-3,
        vcm_steps=60, vcm_batch=1, sample_steps=10, ema_decay=0.995, snr_gamma=5.0),
    # CPU default (SynthTown small, 128x128 folded to 64x64x12: at 128 the fold is what keeps
    # a step near the 64x64 cost).
    # NOTE: measured here (2 shared cores, load ~4): a training step at batch 12 cost 8.0 CPU-s
    # on whole 64x64x12 frames and 0.66 CPU-s on 32x32 crops, so `small` trains on crops, with
    # coordinate channels: without them its whole-frame samples were a collage of crops.
    # NOTE: ACM steps by measurement (docs/skyeyes.md, "What was tried"; load ~2, 0.276 s/step
    # in fp32): held-out FID 295 / 242 / 220 / 201 at 3000 / 6000 / 9000 / 12000 constant-rate
    # steps; decaying the rate over the last 3000 of 12000 steps bettered every metric by about
    # what 1000 more constant steps give; the VCM changed nothing measurable at 300 steps and
    # lowered the warp error at the paper's 3000. bf16 autocast (this machine's CPU has AMX)
    # makes a step 0.28 -> 0.20 s and sampling 2x faster, which pays for both: 72 min from a clean
    # clone with an empty cache, set-up and scoring included (docs/skyeyes.md, Results). On a CPU
    # without native bf16, `--set mixed_precision=no` is faster.
    "small": SkyeyesConfig(
        core=CoreConfig(resolution=128, patch=2, channels=(32, 64, 128), attention=(False, False, True),
                        head_dim=32, embed_dim=64, conditioning="concat", residual=True, residual_scale=2.0,
                        coords=True),
        prior_preset="small", base_steps=0, acm_steps=12000, acm_anneal=3000, acm_batch=16, acm_lr=1e-3,
        train_crop=32, vcm_steps=3000, vcm_batch=1, sample_steps=10, ckpt_every=100, ema_decay=0.995,
        snr_gamma=5.0, mixed_precision="bf16"),
    # NOTE: the paper's VCM wiring. `--set clip_frames=2 --set vcm_local=5 --set vcm_warp=9` (warped
    # sampling) cut the warp error by 35% here (0.0605 against no-VCM's 0.0928) and bettered FVD
    # (613 against 739), but was credibly worse on FID (+16) and LPIPS (+0.012) and rendered 12x
    # slower (3902 s against 335 s): docs/skyeyes.md, "The VCM: what makes frames agree".
    # NOTE: Skyeyes Sec. 4.2: 512x512, ACM 30k iterations at batch 32, VCM 3k iterations at
    # batch 2 (12-frame clips). For GPU users with --pretrained (SD1.5: ControlNet branch,
    # epsilon objective; the base stage is skipped); without it, a ControlNet from scratch.
    "paper": SkyeyesConfig(
        core=CoreConfig(resolution=512, patch=4, channels=(128, 256, 512, 512),
                        attention=(False, True, True, True), layers_per_block=2, head_dim=64,
                        embed_dim=768, norm_groups=32),
        prior_preset="paper", base_steps=30000, base_batch=32, acm_steps=30000, acm_batch=32,
        vcm_steps=3000, vcm_batch=2, sample_steps=50, ckpt_every=1000,
        # NOTE: SD1.5's UNet and a ControlNet branch at batch 32 of 64x64 latents keep their
        # activations in tens of GB; checkpointing them is what fits one 80 GB GPU (not yet
        # measured there: docs/gpu.md). If it still does not fit: --set micro_batches=2.
        grad_checkpointing=True),
}


#: A preset's training where the diffusion stages run on CUDA (`--device cuda`, or "auto" on a
#: machine with a GPU), unless `--set` names the field: the same frames seen, in half the steps at
#: twice the batch. NOTE: on one H200 a `small` ACM step cost 0.051 s at batch 16 (launch
#: overhead: the model is far too small to fill a GPU; ../MEASURED.md, b99d601), so steps, not
#: batch, set a GPU run's time: 12000 steps alone are ~10 min there. Measured on this CPU at
#: `smoke` (docs/gpu.md, against the preset's 600 steps at batch 8, FID 324.5): 300 steps at
#: batch 16 FID 344.9 (LPIPS +0.023 worse), 150 at batch 32 FID 404.2, the same with the rates
#: doubled FID 404.8, each credibly worse: fewer steps cost quality even at equal frames seen,
#: so the trade is the mildest one. Whether `small` at this shape is credibly worse than its
#: CPU row is for a GPU run to show (docs/gpu.md); the CPU presets stay as they are.
GPU_TRAINING = {"small": dict(acm_steps=6000, acm_anneal=1500, acm_batch=32, vcm_steps=1500, vcm_batch=2)}

#: The VCM's own settings, which mean nothing without it: a frame-by-frame method keeps their
#: defaults (its config, cache key and filed rows do not follow the VCM's).
VCM_ONLY = ("clip_frames", "vcm_keys", "vcm_local", "vcm_warp")


def frame_by_frame(config: SkyeyesConfig) -> SkyeyesConfig:
    """`config` without the VCM: vcm off, `VCM_ONLY` at their defaults."""
    defaults = {f.name: f.default for f in dataclasses.fields(SkyeyesConfig) if f.name in VCM_ONLY}
    return dataclasses.replace(config, vcm=False, **defaults)


def baseline_presets(derive) -> dict[str, SkyeyesConfig]:
    """`{preset: derive(Skyeyes' preset without the VCM)}`: the diffusion baselines train with
    Skyeyes' budget at every preset (ACM steps, rate schedule, precision, batch, crops; issue 36),
    so the board compares like with like."""
    return {k: derive(k, frame_by_frame(v)) for k, v in PRESETS.items()}


#: Bumped whenever a change makes old stage checkpoints mean something else (architecture,
#: losses): it is part of every stage cache key. 2: heads sized by `head_dim`. 3: data-parallel
#: batch split, loss weights, VCM in the UNet's down and up blocks only.
STAGE_VERSION = 3


# --------------------------------------------------------------------------- stage 0: priors


def make_prior_method(config: SkyeyesConfig, workdir: Path, seed: int, device: str | None = None) -> Method:
    """The prior method of `config`, on `device` when its config has one."""
    from reference.methods import get_method_class

    cls = get_method_class(config.prior_method)
    extra = {"device": device} if device is not None and has_field(cls.presets[config.prior_preset], "device") else {}
    return cls.from_preset(config.prior_preset, workdir, seed=seed, **extra)


# --------------------------------------------------------------------------- the method


class Skyeyes(Method):
    name = "skyeyes"
    version = "0.1"
    presets = PRESETS
    #: How the condition enters a pretrained SD1.5 UNet (`--pretrained`): the paper's ACM is a
    #: ControlNet branch; the baselines that concatenate their condition (ip2p, gvg) widen conv_in.
    pretrained_conditioning = "controlnet"

    def __init__(self, config: SkyeyesConfig, workdir: Path, *, seed: int = 0, prior_method: Method | None = None,
                 progress: bool = True):
        if config.pretrained:
            # SD1.5's UNet was trained on the epsilon objective and its condition enters through
            # a ControlNet branch (the paper's ACM; the concatenating baselines widen conv_in
            # instead, `pretrained_conditioning`); its fine-tuning keeps both. Its ControlNet
            # takes pixels 8x the latent's size, so no training crops (they would not align).
            # Its noise schedule and objective are the folder's (`pretrained_schedule`), for
            # training and sampling alike, and its learning rate the recipe's (`pretrained_acm_lr`).
            from ..common.diffusion.core import pretrained_schedule

            core_cfg = dataclasses.replace(config.core, pretrained=config.pretrained,
                                           conditioning=self.pretrained_conditioning, residual=False, coords=False,
                                           **pretrained_schedule(config.pretrained))
            config = dataclasses.replace(config, core=core_cfg, sample_strength=1.0, train_crop=0,
                                         acm_lr=config.pretrained_acm_lr)
        if config.sample_strength < 1.0 and not config.core.residual:
            raise ValueError("sample_strength < 1 (an SDEdit start from the prior) needs core.residual")
        if not 0 <= config.acm_anneal < max(config.acm_steps, 1):
            raise ValueError(f"acm_anneal {config.acm_anneal}: expected 0 <= acm_anneal < acm_steps "
                             f"({config.acm_steps}); the decay follows at least one constant-rate step")
        if config.clip_frames < 1:
            raise ValueError(f"clip_frames {config.clip_frames}: expected >= 1")
        if not 0 <= config.vcm_warp <= config.sample_steps or (config.vcm_warp and not config.vcm):
            raise ValueError(f"vcm_warp {config.vcm_warp}: expected 0 <= vcm_warp <= sample_steps "
                             f"({config.sample_steps}), and the VCM on (vcm=true) when it is not 0")
        if config.condition == "aerial" and config.core.residual:
            # the residual from a view taken elsewhere means nothing: diffuse the frames
            config = dataclasses.replace(config, core=dataclasses.replace(config.core, residual=False),
                                         sample_strength=1.0)
        super().__init__(config, workdir, seed=seed, progress=progress)
        self._prior = prior_method  # tests inject a stand-in; else built lazily from the registry
        self.acm = None
        self.vcm = None
        self.conds: dict[str, np.ndarray] = {}  # frame key -> condition image [H, W, 3]
        self.training: dict[str, Any] = {}
        self._figure_written = False
        self._warp = None  # the sequence's warped-sampling targets (`vcm_warp`), set per sequence

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

    # ---------------------------------------------------------------- helpers
    @property
    def prior(self) -> Method:
        if self._prior is None:
            self._prior = self._make_prior()
        return self._prior

    def _make_prior(self) -> Method:
        """The method whose renders are the conditions (stage 0)."""
        return make_prior_method(self.config, self.workdir / "prior", self.seed, self.device)

    # ---------------------------------------------------------------- hooks of the baselines
    def _drop_conditions(self, cond, g):
        """Training conditions [B, C, h, w] as the model sees them, and the text mask [B] (None:
        the prompt everywhere). Skyeyes drops nothing; ip2p drops conditions for guidance."""
        return cond, None

    def _acm_key_extra(self) -> dict:
        """What else the ACM stage depends on (a baseline's own training settings)."""
        return {}

    def _sampling_model(self, model):
        """The model the sampler calls (ip2p: its classifier-free guided combination)."""
        return model

    def config_dict(self) -> dict:
        d = dataclasses.asdict(self.config)
        d["method"] = self.name
        return d

    def _conditions(self, dataset: Dataset | None, scenes: list[Scene]) -> dict[str, np.ndarray]:
        if self.config.condition == "aerial":
            return {frame_key(s, f): nearest_aerial(s, f).image() for s in scenes for f in s.ground}
        conds, cached_s = render_priors(dataset, scenes, self.prior, progress=self.progress, jobs=self.jobs)
        self.cached_s += cached_s
        return conds

    def _to_model(self, images: list[np.ndarray]):
        import torch

        from ..common.diffusion.core import images_to_tensor, resize

        cfg = self.config.core
        return torch.cat([resize(images_to_tensor(im[None]), cfg.resolution) for im in images])

    def _stage_ckpt(self, stage: str, key: dict, steps: int) -> Path:
        """`<cache>/reference/diffusion/<stage>-<hash of everything but the step count>/train-<steps>.pt`,
        started from the furthest shorter run of the same stage (`train.stage_checkpoint`)."""
        from ..common.diffusion.train import stage_checkpoint

        ident = {"stage": stage, "stage_version": STAGE_VERSION, **key}
        return stage_checkpoint(cache_dir() / "reference" / "diffusion" / f"{stage}-{json_sha(ident)[:20]}", steps)

    # ---------------------------------------------------------------- fit
    def fit_train(self, dataset: Dataset) -> None:
        import torch

        from ..common.diffusion import core, train, vcm

        cfg, c = self.config.core, self.config
        acc = train.make_accelerator(self.device, c.mixed_precision)
        scenes = dataset.split("train")
        frames = [(s, f) for s in scenes for f in s.ground]
        with acc.main_process_first():  # under `accelerate launch`, one process fits the priors
            conds = self._conditions(dataset, scenes)
        self.use_threads()  # the prior stage runs single-threaded; the UNet wants every core
        # 1. tensors in model space: targets and conditions, one row per train ground frame; the
        # model diffuses z0 (the frames, or their residual from the prior: `core.to_diffused`).
        x0 = core.encode(self._to_model([f.image() for _, f in frames]), cfg, acc.device)
        cc = core.encode_cond(self._to_model([conds[frame_key(s, f)] for s, f in frames]), cfg, acc.device)
        z0 = core.to_diffused(x0, cc, cfg)
        data_hash = hashlib.sha256(x0.cpu().numpy().tobytes()).hexdigest()
        cond_hash = hashlib.sha256(cc.cpu().numpy().tobytes()).hexdigest()
        sched = core.train_scheduler(cfg)
        n = len(frames)
        gamma = c.snr_gamma or None
        run = dict(accelerator=acc, ema_decay=c.ema_decay, micro_batches=c.micro_batches)

        # 2. base UNet on ground truth: only for a ControlNet branch trained from scratch (a
        # pretrained UNet replaces it; a concat-conditioned UNet is trained whole in stage 3).
        model = core.build_model(cfg, control=False, seed=self.seed)
        if c.grad_checkpointing:  # activations recomputed in backward (memory, not results)
            model.unet.enable_gradient_checkpointing()
        # Stage keys hold everything a stage depends on except its own step count, plus the
        # full identity (with steps) of the stage it starts from.
        base_key = {"core": core.core_key(cfg), "batch": c.base_batch, "lr": c.base_lr, "seed": self.seed,
                    "data": data_hash, "ema": c.ema_decay, "snr_gamma": c.snr_gamma,
                    # autocast changes every stage's numbers (fp32 runs keep their older keys)
                    **({"precision": acc.mixed_precision} if acc.mixed_precision != "no" else {})}
        has_base = cfg.conditioning == "controlnet" and not cfg.pretrained
        if has_base:
            params = core.trainable(model, ["unet.", "prompt"])

            def base_loss(net, g, part):
                idx = torch.randint(0, n, (c.base_batch,), generator=g, device=g.device)
                return train.denoise_loss(net, sched, z0[idx], None, g, part=part, snr_gamma=gamma)

            self.training["base"] = self._run("base", model, params, base_loss, c.base_steps, c.base_lr, base_key, run)
        base_id = {**base_key, "steps": c.base_steps if has_base else 0}

        # 3. ACM: the condition's way in (a ControlNet branch from the UNet, UNet frozen; or the
        # concatenated input of a UNet trained whole).
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.seed + 1)
            model.add_control()
        if c.grad_checkpointing and model.controlnet is not None:
            model.controlnet.enable_gradient_checkpointing()
        acm_key = {"base": base_id, "batch": c.acm_batch, "lr": c.acm_lr, "condition": c.condition,
                   "cond": cond_hash, **self._acm_key_extra()}
        # A concat UNet is trained whole, with its learned text embeddings (a pretrained one's
        # CLIP encodings stay frozen).
        texts = [] if cfg.pretrained else ["prompt"] + (["null_prompt"] if cfg.null_prompt else [])
        params = core.trainable(model, ["controlnet."] if cfg.conditioning == "controlnet" else ["unet.", *texts])

        def acm_loss(net, g, part):
            idx = torch.randint(0, n, (c.acm_batch,), generator=g, device=g.device)
            z, k = train.crops(g, c.train_crop, z0[idx], cc[idx])
            k, text = self._drop_conditions(k, g)
            return train.denoise_loss(net, sched, z, k, g, part=part, snr_gamma=gamma, text=text)

        if not c.acm_anneal:
            self.training["acm"] = self._run("acm", model, params, acm_loss, c.acm_steps, c.acm_lr, acm_key, run)
        else:
            # constant-rate steps (a stage any longer run shares), then the decay phase from them
            stable = c.acm_steps - c.acm_anneal  # >= 1 (checked in __init__)
            const_key, acm_key = acm_key, {"acm": {**acm_key, "steps": stable}, "anneal": c.acm_anneal}
            final = self._stage_ckpt("acm-anneal", acm_key, c.acm_steps)
            if not final.is_file():
                const = self._run("acm", model, params, acm_loss, stable, c.acm_lr, const_key, run)
                # the decay stage reports the constant steps' seconds as resumed (cached) seconds:
                # take off exactly those (the checkpoint's clock, a little short of the stage's
                # own: subtracting the stage's seconds made a fresh run's cached time negative)
                self.cached_s -= train.seed_stage(final.parent, Path(const["checkpoint"]))
            self.training["acm"] = self._run("acm-anneal", model, params, acm_loss, c.acm_steps, c.acm_lr, acm_key,
                                             {**run, "anneal_from": stable}, entry="acm")
        core.trainable(model, [])
        self.acm = model

        # 4. VCM: clip attention in the UNet's down and up blocks of a copy of the frozen ACM;
        # only those layers' projections are trained (the ACM keeps its own, for frame 1).
        if not c.vcm or c.clip_frames == 1:  # 1-frame clips: the ACM frame by frame (`vcm_warp` holds)
            return
        seqs = [[frames.index((s, f)) for f in q.frames] for s in scenes for q in s.sequences.values()]
        seqs = [q for q in seqs if len(q) >= 2]
        f_clip = min(c.clip_frames, min(len(q) for q in seqs))
        vmodel = copy.deepcopy(model)
        vcm.install_vcm(vmodel, vcm.ClipContext(keys=c.vcm_keys), local_window=c.vcm_local, seed=self.seed + 2)
        params = core.trainable(vmodel, vcm.vcm_parameter_names(vmodel))
        vcm_key = {"acm": {**acm_key, "steps": c.acm_steps}, "batch": c.vcm_batch, "lr": c.vcm_lr,
                   "frames": f_clip, "layers": list(vcm.VCM_BLOCKS),
                   # the paper's wiring keeps the keys its stages had before these existed
                   **({"keys": c.vcm_keys} if c.vcm_keys != "clip" else {}),
                   **({"local": c.vcm_local} if c.vcm_local else {})}

        def vcm_loss(net, g, part):
            rows = []
            for _ in range(c.vcm_batch):
                q = seqs[int(torch.randint(0, len(seqs), (1,), generator=g, device=g.device))]
                s0 = int(torch.randint(0, len(q) - f_clip + 1, (1,), generator=g, device=g.device))
                rows.append(q[s0:s0 + f_clip])
            idx = torch.tensor(rows, device=z0.device)  # [B, F]
            z, k = train.crops(g, c.train_crop, z0[idx], cc[idx])
            with vcm.clip_frames(vmodel, f_clip):
                return train.clip_denoise_loss(net, sched, z, k, g, part=part, snr_gamma=gamma)

        self.training["vcm"] = self._run("vcm", vmodel, params, vcm_loss, c.vcm_steps, c.vcm_lr, vcm_key, run)
        core.trainable(vmodel, [])
        self.vcm = vmodel

    def _run(self, stage: str, model, params, loss_fn, steps: int, lr: float, key: dict, run: dict,
             entry: str | None = None) -> dict:
        """Train (or resume) one stage into its cache checkpoint; its summary goes to training.json
        under `entry` (default: the stage's name)."""
        from ..common.diffusion import train

        ckpt = self._stage_ckpt(stage, key, steps)
        res = train.train_loop(model, params, loss_fn, steps=steps, lr=lr, seed=self.seed, ckpt=ckpt,
                               ckpt_every=self.config.ckpt_every, progress=self.progress, desc=stage, **run)
        acc = run["accelerator"]
        tail = res["losses"][-max(1, steps // 10):]
        summary = {"checkpoint": str(ckpt), "steps": res["steps"], "seconds": round(res["seconds"], 2),
                   "cpu_seconds": round(res["cpu_seconds"], 2),
                   "it_per_s": round(res["steps"] / max(res["seconds"], 1e-9), 4),
                   "cpu_s_per_it": round(res["cpu_seconds"] / max(res["steps"], 1), 4),
                   "final_loss": float(np.mean(tail)) if tail else None,
                   "cached_seconds": round(res["resumed_seconds"], 2),
                   "trainable_parameters": sum(p.numel() for p in params),
                   "device": str(acc.device), "processes": acc.num_processes,
                   "mixed_precision": acc.mixed_precision, "micro_batches": self.config.micro_batches,
                   "grad_checkpointing": self.config.grad_checkpointing}
        if run.get("anneal_from") is not None:
            summary["anneal_steps"] = steps - run["anneal_from"]
        self.cached_s += res["resumed_seconds"]
        if acc.is_main_process:
            fileio.write_json(self.workdir / "training.json", {**self.training, entry or stage: summary})
            fileio.write_json(self.workdir / "config.json", self.config_dict())
        return summary

    def fit_scene(self, scene: Scene, *, progress: bool | None = None) -> None:
        """The scene's conditions (its prior renders); the diffusion model is fitted on the train split."""
        self.fit_scenes([scene], progress=progress)

    def fit_scenes(self, scenes: list[Scene], *, progress: bool | None = None) -> None:
        """The scenes' conditions at once: their prior fits run `jobs` at a time (`render_priors`)."""
        if self.acm is None:
            raise RuntimeError(f"{self.name}: fit_train must run before fit_scene")
        self.conds.update(self._conditions(None, scenes))
        if self.config.vcm_warp:  # the prior's depth moves frames: its scene models (cached renders fit none)
            if self.config.prior_method not in ("sugar", "gaussians3d"):
                raise ValueError(f"vcm_warp: the prior {self.config.prior_method!r} is not Gaussians "
                                 "(sugar, gaussians3d), whose depth moves the frames")
            self.prior.fit_scenes([s for s in scenes if s.name not in self.prior._scene_models])

    # ---------------------------------------------------------------- render
    def _generate(self, conds):
        from ..common.diffusion import sample

        seed, c = self._seq_seed, self.config
        acm = self._sampling_model(self.acm)
        if c.vcm:
            return sample.sample_sequence(acm, self.vcm, conds, steps=c.sample_steps, seed=seed,
                                          clip=c.clip_frames, strength=c.sample_strength,
                                          warp=self._warp, hold=c.vcm_warp)
        return sample.sample_frames(acm, conds, steps=c.sample_steps, seed=seed, strength=c.sample_strength)

    def render_sequence(self, scene: Scene, sequence: Sequence) -> Iterator[np.ndarray]:
        from ..common.diffusion import core

        cfg = self.config.core
        priors = [self.conds[frame_key(scene, f)] for f in sequence.frames]
        self.use_threads()
        cc = core.encode_cond(self._to_model(priors), cfg, self.device)
        # Seed per sequence from its id, so frames do not depend on rendering order.
        self._seq_seed = self.seed * 1_000_003 + zlib.crc32(sequence.id.encode())
        self._warp = self._warp_targets(scene, sequence, cc) if self.config.vcm_warp else None
        x = core.from_diffused(self._generate(cc), cc, cfg)
        imgs = core.decode(x, cfg, self.device)  # [N, 3, res, res]
        out = []
        for f, img in zip(sequence.frames, imgs, strict=True):
            img = core.resize(img[None], f.height)[0] if (f.width == f.height) else \
                _resize_hw(img[None], f.height, f.width)[0]
            out.append(core.tensor_to_images(img[None])[0])
        # The figure shows the first sequence rendered in this workdir. A resumed run renders
        # the sequences a killed one left undone first, so it keeps the figure already there.
        if not self._figure_written and not (self.workdir / "figure.png").is_file():
            self._figure_written = True
            write_figure(self.workdir / "figure.png", scene, sequence, priors, out, self.config.figure_frames,
                         condition=self.config.condition)
        yield from out

    def _warp_targets(self, scene: Scene, sequence: Sequence, cc):
        """The warped-sampling targets of a sequence (`vcm_warp`): the prior's depth and the
        poses at the model's resolution."""
        from ..common.diffusion import warp

        res = self.config.core.resolution
        depths = [warp.prior_depth(self.prior, scene, f, res, res) for f in sequence.frames]
        cams = [warp.scaled_camera(f.camera(), res, res) for f in sequence.frames]
        return warp.WarpTargets(cc, depths, cams, self.config.core)


def _resize_hw(images, h: int, w: int):
    import torch.nn.functional as F

    return F.interpolate(images, size=(h, w), mode="bilinear", antialias=True, align_corners=False)


def write_figure(path: Path, scene: Scene, sequence: Sequence, conds: list[np.ndarray],
                 generated: list[np.ndarray], n: int, *, condition: str = "prior") -> None:
    """Rows: nearest aerial view, condition (prior), generated, ground truth; `n` frames spread
    over the sequence. Ground-truth pixels are read here, after generation, for display only."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    idx = np.unique(np.linspace(0, len(sequence) - 1, min(n, len(sequence))).round().astype(int))
    rows = [("aerial (nearest)", [nearest_aerial(scene, sequence.frames[i]).image() for i in idx]),
            (condition, [conds[i][..., :3] for i in idx]),  # the colour of a condition with more channels
            ("generated", [generated[i] for i in idx]),
            ("ground truth", [sequence.frames[i].image() for i in idx])]
    fig, axes = plt.subplots(len(rows), len(idx), figsize=(1.6 * len(idx), 1.7 * len(rows)), squeeze=False)
    for r, (label, imgs) in enumerate(rows):
        for col, (i, im) in enumerate(zip(idx, imgs)):
            ax = axes[r][col]
            ax.imshow(np.clip(im, 0, 1))
            ax.set_xticks([]), ax.set_yticks([])
            if col == 0:
                ax.set_ylabel(label, fontsize=7)
            if r == 0:
                ax.set_title(f"{sequence.name} #{i}", fontsize=7)
    fig.tight_layout()
    with fileio.atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)


class SkyeyesNoVCM(Skyeyes):
    """The paper's ablation: the appearance control module frame by frame (no VCM)."""

    name = "skyeyes-no-vcm"
    presets = {k: frame_by_frame(v) for k, v in PRESETS.items()}
