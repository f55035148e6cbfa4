"""The diffusion core: a diffusers UNet with a ControlNet branch, noise schedules, pixel codec.

Without a pretrained checkpoint the model is trained from scratch in *pixel space*. Images are
mapped to [-1, 1] and, when `patch > 1`, folded losslessly with a pixel-unshuffle
(`[3, H, W] -> [3 p^2, H/p, W/p]`), so a 128x128 image costs the UNet about what a 64x64 one
does. NOTE: measured here (bench/skyeyes.py, 2 CPU cores): a (32, 64, 128) UNet step at batch
12 takes ~4.5x longer on 128x128x3 than on 64x64x12; a trained autoencoder would add a
training stage and a reconstruction-error floor, the unshuffle has neither.

Text conditioning: one embedding for the prompt "a realistic street view image" (Skyeyes
Sec. 4.2). Offline there is no text encoder, so it is a learned "null" embedding
`[1, 1, C]`; with `pretrained=DIR` (a local Stable Diffusion 1.5 diffusers folder) it is the
frozen CLIP encoding of the prompt and the UNet works in the folder's VAE latent space.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from .config import BETA_SCHEDULES, PROMPT, CoreConfig, core_key  # noqa: F401  (PROMPT, core_key: re-exported)

# --------------------------------------------------------------------------- schedulers


class FlowObjective:
    """Training side of the rectified flow (`prediction="flow"`), shaped like the DDPM
    scheduler `train.denoise_loss` uses: integer timesteps t in 0..T are flow times tau = t / T
    (0: the clean sample, which a VCM clip's first frame is given at; training draws 1..T),
    `add_noise` gives z_tau = (1 - tau) z0 + tau flow_noise eps, and the network sees t itself
    as its timestep, as the sampler (`FlowMatchEulerDiscreteScheduler`, timesteps sigma T) does."""

    def __init__(self, cfg: CoreConfig):
        from types import SimpleNamespace

        self.config = SimpleNamespace(num_train_timesteps=cfg.train_timesteps, prediction_type="flow")
        self.noise_scale = cfg.flow_noise

    def tau(self, t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        """Flow times [B] -> [B, 1, ...] broadcastable against `like`."""
        tau = t.to(torch.float32) / self.config.num_train_timesteps
        return tau.view(-1, *([1] * (like.ndim - 1))).to(like.dtype)

    def add_noise(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        tau = self.tau(t, x0)
        return (1.0 - tau) * x0 + tau * self.noise_scale * noise

    def velocity(self, x0: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """d z_tau / d tau: what the network predicts (diffusers' flow-match model output)."""
        return self.noise_scale * noise - x0


def train_scheduler(cfg: CoreConfig):
    """DDPM for training (objective: `cfg.prediction`), or the flow's `FlowObjective`."""
    if cfg.prediction == "flow":
        return FlowObjective(cfg)
    from diffusers import DDPMScheduler

    return DDPMScheduler(num_train_timesteps=cfg.train_timesteps, beta_start=cfg.beta_start,
                         beta_end=cfg.beta_end, beta_schedule=cfg.beta_schedule, prediction_type=cfg.prediction,
                         clip_sample=False)


def sample_scheduler(cfg: CoreConfig):
    """DDIM for sampling: trailing spacing so the first step is t = T - 1 (the noisiest), and
    `set_alpha_to_one` so the last step lands on the clean image (alpha_bar = 1). In pixel
    space the x0 estimate is clipped to the image range [-1, 1] at every step."""
    if cfg.prediction == "flow":
        # Euler steps on sigma = tau from 1 to 0 (shift 1: evenly spaced), timesteps sigma T.
        from diffusers import FlowMatchEulerDiscreteScheduler

        return FlowMatchEulerDiscreteScheduler(num_train_timesteps=cfg.train_timesteps, shift=1.0)
    from diffusers import DDIMScheduler

    return DDIMScheduler(num_train_timesteps=cfg.train_timesteps, beta_start=cfg.beta_start,
                         beta_end=cfg.beta_end, beta_schedule=cfg.beta_schedule, prediction_type=cfg.prediction,
                         clip_sample=cfg.pretrained is None, set_alpha_to_one=True,
                         # a residual of images in [-1, 1] lies in [-2, 2] (times its scale)
                         clip_sample_range=2.0 * cfg.residual_scale if cfg.residual else 1.0,
                         timestep_spacing="trailing")


def pretrained_schedule(root: str | Path) -> dict:
    """The noise schedule a pretrained folder's model was trained on, from its
    `scheduler/scheduler_config.json`, as CoreConfig fields (`train_timesteps`, `beta_start`,
    `beta_end`, `beta_schedule`, `prediction`): training and sampling must use the model's own
    (SD1.5: scaled_linear 0.00085..0.012, epsilon; SD2: v_prediction), not ours from scratch."""
    from skyeyes_bench import inputfiles
    from skyeyes_bench.errors import UserError

    path = Path(root) / "scheduler" / "scheduler_config.json"
    if not path.is_file():
        raise UserError(f"{path}: missing; a diffusers Stable Diffusion folder names its noise schedule there")
    d = inputfiles.read_json(path)
    fields = {"num_train_timesteps": "train_timesteps", "beta_start": "beta_start", "beta_end": "beta_end",
              "beta_schedule": "beta_schedule", "prediction_type": "prediction"}
    out = {}
    for key, field_name in fields.items():
        value = d.get(key, {"prediction_type": "epsilon"}.get(key))  # diffusers' default objective
        ok = {"num_train_timesteps": lambda v: isinstance(v, int) and not isinstance(v, bool) and v > 0,
              "beta_start": lambda v: isinstance(v, (int, float)) and 0 < v < 1,
              "beta_end": lambda v: isinstance(v, (int, float)) and 0 < v < 1,
              "beta_schedule": lambda v: v in BETA_SCHEDULES,
              "prediction_type": lambda v: v in ("epsilon", "v_prediction")}[key]
        if value is None or not ok(value):
            raise UserError(f"{path}: field {key!r} is {value!r}; expected "
                            + {"num_train_timesteps": "a positive integer", "beta_start": "a number in (0, 1)",
                               "beta_end": "a number in (0, 1)",
                               "beta_schedule": " or ".join(BETA_SCHEDULES),
                               "prediction_type": "epsilon or v_prediction"}[key])
        out[field_name] = float(value) if key.startswith("beta_") and key != "beta_schedule" else value
    return out


# --------------------------------------------------------------------------- pixel codec


def resize(images: torch.Tensor, size: int) -> torch.Tensor:
    """[N, C, H, W] -> [N, C, size, size], antialiased bilinear (identity if already that size)."""
    if images.shape[-2:] == (size, size):
        return images
    return F.interpolate(images, size=(size, size), mode="bilinear", antialias=True, align_corners=False)


def resize_hw(images: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """[N, C, H, W] -> [N, C, h, w], antialiased bilinear (a frame that is not square)."""
    return F.interpolate(images, size=(h, w), mode="bilinear", antialias=True, align_corners=False)


#: Frames per VAE call (`--pretrained`): a whole train split at 512x512 in one call does not fit
#: a GPU (at `paper` size 3072 frames, ~100 GB of activations); 16 frames take ~3 GB.
VAE_CHUNK = 16


def _vae_chunks(fn, x: torch.Tensor, device) -> torch.Tensor:
    """`fn` (a VAE encode or decode) over `x` [N, ...] in chunks of `VAE_CHUNK` on `device` (None:
    where `x` is); the result comes back to `x`'s device."""
    dev = x.device if device is None else torch.device(device)
    with torch.no_grad():
        return torch.cat([fn(x[i:i + VAE_CHUNK].to(dev)).to(x.device) for i in range(0, len(x), VAE_CHUNK)])


def encode(images: torch.Tensor, cfg: CoreConfig, device=None) -> torch.Tensor:
    """Images [N, 3, res, res] in [0, 1] -> model space [N, 3 p^2, res/p, res/p] in [-1, 1]
    (or the VAE latent [N, 4, res/8, res/8] of a pretrained folder, computed on `device` in
    chunks and returned where `images` are)."""
    assert images.ndim == 4 and images.shape[1] == 3, images.shape
    x = images * 2.0 - 1.0
    if cfg.pretrained:
        vae = _vae(cfg.pretrained, device or x.device)
        return _vae_chunks(lambda c: vae.encode(c).latent_dist.mean * vae.config.scaling_factor, x, device)
    return F.pixel_unshuffle(x, cfg.patch) if cfg.patch > 1 else x


def encode_cond(images: torch.Tensor, cfg: CoreConfig, device=None) -> torch.Tensor:
    """Condition images [N, 3 + cfg.cond_extra, res, res] in [0, 1] -> the condition in model
    space: the colour image encoded as the sample is (unshuffled pixels, or the VAE latent of a
    pretrained folder), then the extra channels (mapped to [-1, 1] and folded alike, or
    area-averaged onto the latent grid), then the x, y coordinate channels with `cfg.coords`.
    A pretrained ControlNet branch takes the raw [0, 1] pixels instead. `device`: where the VAE
    runs (`encode`)."""
    assert images.ndim == 4 and images.shape[1] == 3 + cfg.cond_extra, (images.shape, cfg.cond_extra)
    if cfg.pretrained and cfg.conditioning == "controlnet":
        return images
    c = encode(images[:, :3], cfg, device)
    if cfg.cond_extra:
        extra = images[:, 3:] * 2.0 - 1.0
        if cfg.pretrained:
            extra = F.interpolate(extra, size=tuple(c.shape[-2:]), mode="area")
        elif cfg.patch > 1:
            extra = F.pixel_unshuffle(extra, cfg.patch)
        c = torch.cat([c, extra.to(c.dtype)], dim=1)
    if not cfg.coords:
        return c
    n, _, h, w = c.shape
    ys = torch.linspace(-1.0, 1.0, h, dtype=c.dtype, device=c.device)
    xs = torch.linspace(-1.0, 1.0, w, dtype=c.dtype, device=c.device)
    grid = torch.stack([xs[None, :].expand(h, w), ys[:, None].expand(h, w)])  # [2, h, w]: x, y
    return torch.cat([c, grid.expand(n, 2, h, w)], dim=1)


def sample_shape(cond_shape: tuple[int, ...], cfg: CoreConfig) -> tuple[int, ...]:
    """Shape of the diffused samples for conditions of `cond_shape` [N, C, H, W]: the same in
    pixel space (and for a concatenated latent condition); with a pretrained ControlNet the
    condition is [0, 1] pixels and the sample is the VAE latent, 8x smaller with 4 channels."""
    n, _, h, w = cond_shape
    if cfg.pretrained and cfg.conditioning == "controlnet":
        return (n, cfg.sample_channels, h // 8, w // 8)
    return (n, cfg.sample_channels, h, w)


def decode(x: torch.Tensor, cfg: CoreConfig, device=None) -> torch.Tensor:
    """Model space [N, C, h, w] -> images [N, 3, res, res] in [0, 1] (clamped); a pretrained
    folder's VAE decodes on `device` in chunks (`encode`)."""
    if cfg.pretrained:
        vae = _vae(cfg.pretrained, device or x.device)
        x = _vae_chunks(lambda c: vae.decode(c / vae.config.scaling_factor).sample, x, device)
    elif cfg.patch > 1:
        x = F.pixel_shuffle(x, cfg.patch)
    return ((x + 1.0) / 2.0).clamp(0.0, 1.0)


_VAES: dict = {}


def _vae(root: str, device):
    """The folder's VAE (loaded once), on `device`."""
    if root not in _VAES:
        from diffusers import AutoencoderKL

        _VAES[root] = AutoencoderKL.from_pretrained(Path(root) / "vae", local_files_only=True).eval()
    return _VAES[root].to(device)


def images_to_tensor(images) -> torch.Tensor:
    """numpy float32 [N, H, W, C] in [0, 1] -> torch [N, C, H, W] (C = 3, or more for a
    condition with extra channels)."""
    t = torch.as_tensor(images, dtype=torch.float32, device="cpu")  # frames are read on the host
    assert t.ndim == 4 and t.shape[-1] >= 3, t.shape
    return t.permute(0, 3, 1, 2).contiguous()


def tensor_to_images(t: torch.Tensor):
    """torch [N, 3, H, W] -> numpy float32 [N, H, W, 3]."""
    return t.detach().permute(0, 2, 3, 1).contiguous().numpy().astype("float32")


# --------------------------------------------------------------------------- model


def build_unet(cfg: CoreConfig):
    from diffusers import UNet2DConditionModel

    down = tuple("CrossAttnDownBlock2D" if a else "DownBlock2D" for a in cfg.attention)
    up = tuple("CrossAttnUpBlock2D" if a else "UpBlock2D" for a in reversed(cfg.attention))
    return UNet2DConditionModel(
        sample_size=cfg.latent_size, in_channels=cfg.in_channels, out_channels=cfg.sample_channels,
        down_block_types=down, up_block_types=up, mid_block_type="UNetMidBlock2DCrossAttn",
        block_out_channels=tuple(cfg.channels), layers_per_block=cfg.layers_per_block,
        # NOTE: diffusers' UNet2DConditionModel reads `attention_head_dim` as the number of
        # heads (its docstring says so; a legacy naming quirk), so pass heads = width / head_dim.
        cross_attention_dim=cfg.embed_dim, attention_head_dim=cfg.heads_per_level,
        norm_num_groups=cfg.norm_groups,
    )


class ControlledUNet(nn.Module):
    """UNet + optional ControlNet branch + the prompt embedding, as one module.

    `forward(x_t, t, cond)` predicts the noise epsilon (or v, per `cfg.prediction`). The ControlNet branch is created by
    `add_control()` (diffusers `ControlNetModel.from_unet`: a copy of the UNet's encoder and
    middle block with zero-initialised output convolutions, so at creation the controlled
    model predicts exactly what the UNet alone predicts).
    """

    def __init__(self, cfg: CoreConfig):
        super().__init__()
        self.cfg = cfg
        self.unet = build_unet(cfg)
        self.controlnet = None
        # Learned null embedding standing in for the text-encoded prompt. Small init so the
        # cross-attention starts near a constant bias.
        # Built on the host like the UNet's own layers; the training loop moves the model.
        self.prompt = nn.Parameter(torch.randn(1, 1, cfg.embed_dim, device="cpu") * 0.02)
        # The unconditional text (classifier-free guidance on the text): a second learned
        # embedding, created after the others so models without it initialise as before.
        self.null_prompt = (nn.Parameter(torch.randn(1, 1, cfg.embed_dim, device="cpu") * 0.02)
                            if cfg.null_prompt else None)

    def add_control(self) -> None:
        """Give the model its condition input: a ControlNet branch (`conditioning="controlnet"`);
        with `"concat"` the UNet's input already has the condition's channels (nothing to add)."""
        from diffusers import ControlNetModel

        if self.cfg.conditioning == "concat":
            return
        if self.cfg.pretrained:
            # SD1.5 layout: the branch takes [0, 1] pixels and downsamples them 8x to the latent.
            root = Path(self.cfg.pretrained) / "controlnet"
            self.controlnet = (ControlNetModel.from_pretrained(root, local_files_only=True)
                               if (root / "config.json").is_file() else ControlNetModel.from_unet(self.unet))
            return
        # Pixel space: the condition has the sample's layout, so no downsampling in its embedding.
        self.controlnet = ControlNetModel.from_unet(
            self.unet, conditioning_embedding_out_channels=(16,), conditioning_channels=self.cfg.sample_channels)

    @property
    def conditioned(self) -> bool:
        return self.cfg.conditioning == "concat" or self.controlnet is not None

    def text_embedding(self, b: int, text: torch.Tensor | None = None) -> torch.Tensor:
        """The cross-attention input [b, L, C]: the prompt for every row, or, where `text` [b]
        (bool) is False, the unconditional embedding (`cfg.null_prompt`)."""
        if text is None:
            return self.prompt.expand(b, -1, -1)
        assert self.null_prompt is not None, "text dropout needs cfg.null_prompt (the unconditional embedding)"
        assert text.shape == (b,) and text.dtype == torch.bool, (text.shape, text.dtype)
        on = text.to(self.prompt.device)[:, None, None]
        return torch.where(on, self.prompt.expand(b, -1, -1), self.null_prompt.expand(b, -1, -1))

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, cond: torch.Tensor | None = None,
                text: torch.Tensor | None = None) -> torch.Tensor:
        """x_t [B, C, h, w] noisy, t [B] integer timesteps, cond [B, C, h, w] (model space),
        text [B] bool or None (rows given the prompt; None: all) -> the prediction [B, C, h, w]
        (epsilon, v or the flow's velocity, per `cfg.prediction`)."""
        b = x_t.shape[0]
        assert t.shape == (b,), (t.shape, b)
        emb = self.text_embedding(b, text)
        if self.cfg.conditioning == "concat":
            assert cond is not None and cond.shape == (b, self.cfg.cond_channels, *x_t.shape[2:]), \
                "a concat-conditioned model needs a condition of cfg.cond_channels"
            return self.unet(torch.cat([x_t, cond], dim=1), t, encoder_hidden_states=emb, return_dict=False)[0]
        down = mid = None
        if self.controlnet is not None:
            assert cond is not None and cond.shape[0] == b, "a controlled model needs a condition"
            down, mid = self.controlnet(x_t, t, encoder_hidden_states=emb, controlnet_cond=cond,
                                        return_dict=False)
        return self.unet(x_t, t, encoder_hidden_states=emb, down_block_additional_residuals=down,
                         mid_block_additional_residual=mid, return_dict=False)[0]


def to_diffused(x0: torch.Tensor, cond: torch.Tensor | None, cfg: CoreConfig) -> torch.Tensor:
    """Model-space images -> the variable the model diffuses: x0 itself, or with `cfg.residual`
    the scaled residual (x0 - cond) * residual_scale."""
    return (x0 - _prior(cond, cfg)) * cfg.residual_scale if cfg.residual else x0


def from_diffused(z: torch.Tensor, cond: torch.Tensor | None, cfg: CoreConfig) -> torch.Tensor:
    """Inverse of `to_diffused`."""
    return _prior(cond, cfg) + z / cfg.residual_scale if cfg.residual else z


def _prior(cond: torch.Tensor, cfg: CoreConfig) -> torch.Tensor:
    """The condition's image channels [..., C, h, w] (without the coordinate channels)."""
    return cond.narrow(-3, 0, cfg.sample_channels)


def build_model(cfg: CoreConfig, *, control: bool, seed: int = 0) -> ControlledUNet:
    """A freshly initialised model (deterministic in `seed`)."""
    if cfg.pretrained:
        return load_pretrained(cfg, control=control)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = ControlledUNet(cfg)
        if control:
            model.add_control()
    return model


def load_pretrained(cfg: CoreConfig, *, control: bool) -> ControlledUNet:
    """UNet (and ControlNet if the folder has one) from a local SD1.5 diffusers folder.

    NOTE: this path cannot be exercised offline (no checkpoint, no `transformers`); it follows
    the diffusers folder layout (unet/, text_encoder/, tokenizer/, vae/, optional controlnet/).
    The VAE latent space (8x downsampling, 4 channels) replaces the pixel codec (`encode`,
    `decode`); the prompt (`cfg.prompt_text`, and the empty prompt with `cfg.null_prompt`) is
    encoded once by the frozen CLIP text encoder. With `conditioning="concat"` the condition's
    latent (and extra channels) enter through the UNet's first convolution, widened with
    zero-initialised inputs (`widen_conv_in`, as InstructPix2Pix does).
    """
    from skyeyes_bench.errors import UserError

    root = Path(cfg.pretrained)
    if not (root / "unet" / "config.json").is_file():
        raise UserError(f"{root}: not a diffusers Stable Diffusion folder (expected unet/config.json)")
    try:
        from transformers import CLIPTextModel, CLIPTokenizer
    except ImportError:
        raise UserError("--pretrained needs the 'transformers' package for the text encoder; pip install transformers") from None
    from diffusers import UNet2DConditionModel

    model = ControlledUNet.__new__(ControlledUNet)
    nn.Module.__init__(model)
    model.cfg = cfg
    model.unet = UNet2DConditionModel.from_pretrained(root / "unet", local_files_only=True)
    if cfg.conditioning == "concat":
        widen_conv_in(model.unet, cfg.in_channels)
    tok = CLIPTokenizer.from_pretrained(root / "tokenizer", local_files_only=True)
    enc = CLIPTextModel.from_pretrained(root / "text_encoder", local_files_only=True)
    with torch.no_grad():
        # CLIP's context is 77 tokens (its position table); some tokenizer folders leave
        # model_max_length unset (a huge sentinel), so the encoder's length is the one to pad to.
        length = min(tok.model_max_length, enc.config.max_position_embeddings)
        texts = [cfg.prompt_text] + ([""] if cfg.null_prompt else [])
        ids = tok(texts, padding="max_length", max_length=length, truncation=True, return_tensors="pt").input_ids
        emb = enc(ids)[0]  # [1 or 2, 77, 768]
    model.prompt = nn.Parameter(emb[:1], requires_grad=False)
    # NOTE: the unconditional text of SD and InstructPix2Pix is the encoded empty prompt.
    model.null_prompt = nn.Parameter(emb[1:2], requires_grad=False) if cfg.null_prompt else None
    model.controlnet = None
    if control:
        model.add_control()
    return model


def widen_conv_in(unet, in_channels: int) -> None:
    """Give a pretrained UNet's first convolution `in_channels` inputs, the new ones with zero
    weights, so the widened UNet computes exactly what it did on its old inputs whatever the new
    channels hold (InstructPix2Pix, Brooks et al. 2023, Sec. 3.2: the image conditioning's
    extra input channels of the first layer start at zero)."""
    old = unet.conv_in
    if old.in_channels == in_channels:
        return
    if old.in_channels > in_channels:
        raise ValueError(f"conv_in has {old.in_channels} inputs, more than the {in_channels} asked for")
    new = nn.Conv2d(in_channels, old.out_channels, old.kernel_size, stride=old.stride, padding=old.padding,
                    bias=old.bias is not None).to(old.weight.device, old.weight.dtype)
    with torch.no_grad():
        new.weight.zero_()
        new.weight[:, :old.in_channels] = old.weight
        if old.bias is not None:
            new.bias.copy_(old.bias)
    unet.conv_in = new
    unet.register_to_config(in_channels=in_channels)


def device_of(model: nn.Module) -> torch.device:
    """Where `model`'s parameters live (the CPU for a model without any)."""
    return next((p.device for p in model.parameters()), torch.device("cpu"))


def trainable(model: nn.Module, names: list[str] | None = None) -> list[nn.Parameter]:
    """Freeze everything, then unfreeze parameters whose name starts with one of `names`
    (all if None). Returns the unfrozen parameters in a stable order."""
    out = []
    for n, p in model.named_parameters():
        on = names is None or any(n.startswith(k) for k in names)
        p.requires_grad_(on)
        if on:
            out.append(p)
    return out


def replace_config(cfg: CoreConfig, **kw) -> CoreConfig:
    return dataclasses.replace(cfg, **kw)
