"""Diffusion core shared by Skyeyes and the ControlNet baseline.

- `core`: `CoreConfig`, `ControlledUNet` (diffusers UNet2DConditionModel + ControlNetModel
  branch + prompt embedding), DDPM/DDIM schedulers, pixel codec.
- `vcm`: the view consistency module as a diffusers attention processor.
- `train`: denoising losses (epsilon or v) (frames, first-frame-conditioned clips), resumable training loop.
- `sample`: DDIM sampling frame by frame and autoregressively clip by clip.
- `guidance`: classifier-free guidance on image and text (InstructPix2Pix): condition dropout, guided predictions.
"""

from .core import CoreConfig, ControlledUNet, build_model, decode, encode, encode_cond, sample_scheduler, train_scheduler
from .sample import ddim, ddim_clip, sample_frames, sample_sequence
from .train import clip_denoise_loss, denoise_loss, train_loop
from .vcm import clip_frames, install_vcm, vcm_parameter_names

__all__ = [
    "CoreConfig", "ControlledUNet", "build_model", "decode", "encode", "encode_cond",
    "sample_scheduler", "train_scheduler", "ddim", "ddim_clip", "sample_frames", "sample_sequence",
    "clip_denoise_loss", "denoise_loss", "train_loop", "clip_frames", "install_vcm", "vcm_parameter_names",
]
