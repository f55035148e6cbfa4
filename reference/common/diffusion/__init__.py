"""The diffusion family (Skyeyes, skyeyes-no-vcm, controlnet, ip2p, gvg): one pipeline of small parts.

- `pipeline`: `DiffusionMethod`, the family's `Method` (fit the stages, make the conditions,
  sample), and what a member chooses (its condition, guidance, presets, VCM on or off).
- `conditions`: what conditions the model (a prior's renders, the nearest aerial view).
- `guidance`: how it is guided: none, or classifier-free on image and text (InstructPix2Pix:
  condition dropout in training, guided predictions at sampling).
- `stages`: the training stages (base UNet, ACM, VCM) and their cache keys.
- `config`: `CoreConfig` (the denoiser), `DiffusionConfig` (a run of any member); `presets`: the
  family's presets (Skyeyes' formulation and training budget).
- `core`: `ControlledUNet` (diffusers UNet2DConditionModel + ControlNetModel branch + prompt
  embedding), DDPM/DDIM schedulers, pixel codec.
- `vcm`: the view consistency module as a diffusers attention processor.
- `train`: denoising losses (epsilon or v) (frames, first-frame-conditioned clips), resumable training loop.
- `sample`: DDIM sampling frame by frame and autoregressively clip by clip.
- `additions`: our steps beyond the paper (carried noise, prior anchor, street, sky), each a
  component with its own config, run only by the members that name them (`skyeyes-geo`).
- `figure`: a run's figure (aerial, condition, generated, ground truth).
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
