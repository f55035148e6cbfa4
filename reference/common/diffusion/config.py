"""The configs of the diffusion family: the denoiser's architecture (`CoreConfig`) and a run's
(`DiffusionConfig`: the stages, their training budget, sampling, devices), which every member
(Skyeyes, its no-VCM ablation, controlnet, ip2p, gvg) has, or extends with its own fields.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

#: NOTE: the uniform prompt of Skyeyes, Sec. 4.2 (Implementation Details).
PROMPT = "a realistic street view image"


#: The noise schedules of diffusers' DDPM/DDIM schedulers that a pretrained folder may name.
BETA_SCHEDULES = ("linear", "scaled_linear", "squaredcos_cap_v2")


@dataclass(frozen=True)
class CoreConfig:
    """Architecture of the denoiser. Sizes in pixels; `channels` per UNet level."""

    resolution: int = 64  # model input size in pixels (square); frames are resized to it
    patch: int = 1  # pixel-unshuffle factor: the UNet sees [3 p^2, res/p, res/p]
    channels: tuple[int, ...] = (32, 64, 128)
    attention: tuple[bool, ...] = (False, True, True)  # transformer blocks (attn1 + attn2) per level
    layers_per_block: int = 1
    head_dim: int = 32
    embed_dim: int = 64  # width of the prompt embedding (cross-attention dim)
    norm_groups: int = 8
    train_timesteps: int = 1000
    # NOTE: Ho et al. 2020 linear schedule (1e-4 .. 0.02, T = 1000): alpha_bar_T = 4.0e-5, i.e.
    # pure noise at t = T up to 0.6 % signal amplitude.
    beta_start: float = 1e-4
    beta_end: float = 0.02
    # diffusers' `beta_schedule`: "linear" (ours from scratch) or, with `pretrained`, the folder's
    # own (SD1.5: "scaled_linear" 0.00085..0.012; `pretrained_schedule`).
    beta_schedule: str = "linear"
    # What the network predicts (diffusers' `prediction_type`): "epsilon" (the paper's objective,
    # SD1.5's; forced with --pretrained) or "v_prediction" (Salimans & Ho 2022, v = sqrt(ab) eps -
    # sqrt(1 - ab) x0), the default for models trained from scratch. NOTE: measured on SynthTown smoke (250 +
    # 250 steps): with epsilon, x0 = (x_t - sqrt(1 - ab) eps) / sqrt(ab) amplifies the residual
    # epsilon error ~3x at t = 500 and ~160x at t = T, so the DDIM trajectory never locks on and
    # frames come out as noise (x0 error 0.18 vs a signal variance of 0.13); v keeps the x0 error
    # bounded at every t. See docs/skyeyes.md for the figures.
    #
    # "flow": rectified flow (Liu et al. 2023; SD3's convention, Esser et al. 2024): the sample
    # at flow time tau in [0, 1] is z_tau = (1 - tau) z0 + tau flow_noise eps, the network
    # predicts the velocity dz/dtau = flow_noise eps - z0, and sampling integrates it from
    # tau = 1 to 0 with diffusers' FlowMatchEulerDiscreteScheduler. With `residual`, tau = 1 is
    # the prior plus noise of std `flow_noise`: a bridge from the prior to the frame, as
    # ResShift (Yue et al., NeurIPS 2023) and I2SB (Liu et al., ICML 2023) start restoration
    # from the degraded image. A small `flow_noise` keeps the sample near its prior's layout
    # from the first step; 1 is the usual noise-to-data flow.
    prediction: str = "v_prediction"
    flow_noise: float = 1.0
    pretrained: str | None = None  # local SD1.5 diffusers folder
    # How the condition (prior) enters the denoiser: "controlnet" (the paper's ACM: a
    # ControlNet branch beside a UNet, the pretrained path) or "concat" (the condition is
    # concatenated to the noisy sample at the UNet's input, as SR3, Palette and
    # InstructPix2Pix do: the model sees it from its first step, with no zero convolutions to
    # grow first). See docs/skyeyes.md for the measurements behind the CPU presets' choice.
    conditioning: str = "controlnet"
    # Diffuse the residual (x0 - condition) * residual_scale instead of x0 (concat only): an
    # untrained model's x0 estimate is then the condition itself, not a grey frame.
    residual: bool = False
    residual_scale: float = 1.0
    # Two pixel-coordinate channels (x, y in [-1, 1] over the whole frame) appended to the
    # concatenated condition, so a model trained on crops knows where in the frame each crop
    # lies (Patch Diffusion, Wang et al., NeurIPS 2023). Measured on SynthTown small: without
    # them a crop-trained model samples whole frames as a collage (docs/skyeyes.md).
    coords: bool = False
    # Extra condition channels beyond the condition image's 3 colours, in image space, each in
    # [0, 1] (gvg: the projected depth and the mask of what the aerial views saw). They follow
    # the colour channels, folded like them (`patch`); with `pretrained`, area-averaged onto the
    # latent grid. Concat only.
    cond_extra: int = 0
    # A second text embedding, the unconditional one, beside the prompt: a learned "null"
    # embedding (or, with `pretrained`, the CLIP encoding of the empty prompt), so that
    # classifier-free guidance on the text has an unconditional branch (InstructPix2Pix).
    null_prompt: bool = False
    # The text the prompt embedding stands for (encoded with `pretrained`; a label otherwise).
    prompt_text: str = PROMPT

    def __post_init__(self):
        if self.prediction not in ("epsilon", "v_prediction", "flow"):
            raise ValueError(f"prediction {self.prediction!r}: expected 'epsilon', 'v_prediction' or 'flow'")
        if not self.flow_noise > 0:
            raise ValueError(f"flow_noise {self.flow_noise}: expected > 0")
        if self.conditioning not in ("controlnet", "concat"):
            raise ValueError(f"conditioning {self.conditioning!r}: expected 'controlnet' or 'concat'")
        if self.residual and self.conditioning != "concat":
            raise ValueError("residual diffusion needs conditioning='concat'")
        if self.coords and self.conditioning != "concat":
            raise ValueError("coordinate channels need conditioning='concat'")
        if self.beta_schedule not in BETA_SCHEDULES:
            raise ValueError(f"beta_schedule {self.beta_schedule!r}: expected one of {', '.join(BETA_SCHEDULES)}")
        if self.cond_extra < 0 or (self.cond_extra and self.conditioning != "concat"):
            raise ValueError(f"cond_extra {self.cond_extra}: extra condition channels need "
                             "conditioning='concat' and a count >= 0")

    @property
    def sample_channels(self) -> int:
        """Channels of the diffused sample: SD VAE latents have 4; pixels folded p x p have 3 p^2."""
        return 4 if self.pretrained else 3 * self.patch**2

    @property
    def extra_channels(self) -> int:
        """Model-space channels of the `cond_extra` image channels (folded p x p, or one each on
        the latent grid)."""
        return self.cond_extra * (1 if self.pretrained else self.patch**2)

    @property
    def cond_channels(self) -> int:
        """Channels of the condition in model space: the sample's (the colour image), the extra
        channels', plus 2 with `coords`."""
        return self.sample_channels + self.extra_channels + (2 if self.coords else 0)

    @property
    def image_cond_channels(self) -> int:
        """The condition's channels that carry the conditioning images (all but the coordinates):
        what a dropped condition sets to zero."""
        return self.sample_channels + self.extra_channels

    @property
    def in_channels(self) -> int:
        """Channels of the UNet's input (the sample, plus the condition when concatenated)."""
        return self.sample_channels + (self.cond_channels if self.conditioning == "concat" else 0)

    @property
    def heads_per_level(self) -> tuple[int, ...]:
        """Attention heads per UNet level, so that each head is `head_dim` wide."""
        return tuple(max(1, c // self.head_dim) for c in self.channels)

    @property
    def latent_size(self) -> int:
        return self.resolution // (8 if self.pretrained else self.patch)


#: Fields added after stage checkpoints were first cached: left out of `core_key` while at their
#: defaults, so the stages cached before they existed keep their keys.
_KEY_OMITTED_AT_DEFAULT = ("cond_extra", "null_prompt", "prompt_text", "beta_schedule")


def core_key(cfg: CoreConfig) -> dict:
    """The config as a stage cache key (`dataclasses.asdict`, without the later fields that are
    at their defaults, and without `flow_noise` unless the objective is the flow: it changes
    nothing then)."""
    d = dataclasses.asdict(cfg)
    defaults = CoreConfig()
    for k in _KEY_OMITTED_AT_DEFAULT:
        if d[k] == getattr(defaults, k):
            del d[k]
    if cfg.prediction != "flow":
        del d["flow_noise"]
    return d


def core_config_from_dict(d: dict) -> CoreConfig:
    d = dict(d)
    for k in ("channels", "attention"):
        if k in d:
            d[k] = tuple(d[k])
    return CoreConfig(**d)


# --------------------------------------------------------------------------- a run


@dataclass(frozen=True)
class DiffusionConfig:
    """Everything a run of a diffusion method depends on (Skyeyes and its baselines). Steps are optimiser iterations; batches count frames
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
    # frame in sequence order.
    clip_frames: int = 12
    # Which frames a frame attends to in the rewired self-attention (`vcm.KEYS`: "clip", every
    # frame of its clip, the paper's; "previous", its own and the previous frame's tokens).
    vcm_keys: str = "clip"
    # Local attention of each token over the previous frame's window x window neighbourhood after
    # every resnet of the UNet's levels without self-attention (`vcm.LocalFrameAttention`; 0: none).
    vcm_local: int = 0
    # The paper's clip attention as new layers after every resnet of this many of the UNet's levels
    # without self-attention, the coarsest first (`vcm.ClipFrameAttention`; 0: none): SD1.5 attends
    # at three of four levels, `small`'s UNet at its coarsest only.
    vcm_levels: int = 0
    # The VCM's training crop (model-space pixels; -1: `train_crop`'s; 0: whole frames, what
    # sampling sees: its attention then spans the tokens of whole frames, not a crop's quarter).
    vcm_crop: int = -1
    # The VCM's loss weights (-1: `snr_gamma`'s; 0: uniform; else min-SNR-gamma). Min-SNR weights a v
    # target's x0 error by min(SNR, gamma): near 0 at the noisiest steps, where sampling from pure
    # noise decides a frame's colours and where the first frame has the most to tell.
    vcm_snr_gamma: float = -1.0
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
    # torch.compile of the network the training stages step ("" eager; or a torch.compile mode:
    # "default", "reduce-overhead" (CUDA graphs on a GPU: for a model too small to fill one, whose
    # step is launch overhead), "max-autotune-no-cudagraphs"). The same training up to float
    # rounding, so not in the stage keys; off in every preset until measured on a GPU (docs/gpu.md).
    compile: str = ""
    figure_frames: int = 6
    # torch threads of the diffusion stages (0: every core; OMP_NUM_THREADS wins when set).
    # NOTE: measured on SynthTown small, base stage: 2.4 s/step on 1 thread (the setting the
    # SuGaR prior leaves behind) on an otherwise idle 2-core machine.
    threads: int = 0


#: `pretrained_acm_lr` of the baselines that fine-tune a pretrained UNet whole, its conv_in
#: widened for the concatenated condition (ip2p, gvg). NOTE: InstructPix2Pix (Brooks et al.
#: 2023), its training details: learning rate 1e-4, no warm-up.
WHOLE_UNET_LR = 1e-4

#: The VCM's own settings, which mean nothing without it: a frame-by-frame method keeps their
#: defaults (its config, cache key and filed rows do not follow the VCM's).
VCM_ONLY = ("clip_frames", "vcm_keys", "vcm_local", "vcm_levels", "vcm_crop", "vcm_snr_gamma")


def frame_by_frame(config: DiffusionConfig) -> DiffusionConfig:
    """`config` without the VCM: vcm off, `VCM_ONLY` at their defaults."""
    defaults = {f.name: f.default for f in dataclasses.fields(DiffusionConfig) if f.name in VCM_ONLY}
    return dataclasses.replace(config, vcm=False, **defaults)

