"""Classifier-free guidance on two conditions, image and text (InstructPix2Pix, Brooks et al.,
CVPR 2023, Sec. 3.2.1): conditions dropped during training, and the guided prediction at
sampling.

Training drops, per example and independently of everything else, only the image condition
with probability `p_image`, only the text with `p_text`, and both with `p_both` (IP2P: 5% each).
A dropped image is the *null* condition: its image channels set to zero in model space (IP2P
zeroes the image latent; here a zero is also the mid-grey pixel), the coordinate channels kept,
since they say where a pixel is, not what the image shows. A dropped text is the unconditional
embedding (`CoreConfig.null_prompt`).

Sampling (IP2P Sec. 3.2.1): e = e(0, 0) + s_I (e(c_I, 0) - e(0, 0)) + s_T (e(c_I, c_T) - e(c_I, 0)).
The weights of the three predictions sum to 1, so the same combination of v or flow-velocity
predictions is the combination of the epsilon (or x0) estimates they stand for: at a fixed x_t
each is an affine function of the others.
"""

from __future__ import annotations

import torch
from torch import nn

from .core import CoreConfig

#: NOTE: InstructPix2Pix's default guidance scales (Brooks et al. 2023; diffusers'
#: StableDiffusionInstructPix2PixPipeline: image_guidance_scale=1.5, guidance_scale=7.5).
IMAGE_SCALE = 1.5
TEXT_SCALE = 7.5
#: NOTE: InstructPix2Pix Sec. 3.2.1: c_I alone dropped for 5% of examples, c_T alone for 5%, both for 5%.
DROP = 0.05


def check_drops(p_image: float, p_text: float, p_both: float) -> None:
    """ValueError unless the three drop probabilities are >= 0 and sum to at most 1."""
    if min(p_image, p_text, p_both) < 0 or p_image + p_text + p_both > 1:
        raise ValueError(f"drop probabilities {p_image}, {p_text}, {p_both}: expected >= 0, summing to <= 1")


def draw_drops(b: int, g: torch.Generator, p_image: float, p_text: float,
               p_both: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Which of b examples lose their image condition and which their text: (drop_image [b],
    drop_text [b]) bool. One uniform draw per example from `g` picks one of four exclusive cases:
    image only (p_image), text only (p_text), both (p_both), neither (the rest)."""
    check_drops(p_image, p_text, p_both)
    u = torch.rand(b, generator=g, dtype=torch.float64, device=g.device)
    image_only = u < p_image
    text_only = (u >= p_image) & (u < p_image + p_text)
    both = (u >= p_image + p_text) & (u < p_image + p_text + p_both)
    return image_only | both, text_only | both


def null_condition(cond: torch.Tensor, cfg: CoreConfig, rows: torch.Tensor | None = None) -> torch.Tensor:
    """cond [B, C, h, w] (model space) with the image channels of `rows` [B] bool (all if None)
    set to zero; coordinate channels and the other rows unchanged. Returns a new tensor."""
    assert cond.ndim == 4 and cond.shape[1] == cfg.cond_channels, (cond.shape, cfg.cond_channels)
    out = cond.clone()
    k = cfg.image_cond_channels
    if rows is None:
        out[:, :k] = 0
    else:
        assert rows.shape == (cond.shape[0],) and rows.dtype == torch.bool, rows.shape
        out[rows.to(cond.device), :k] = 0
    return out


def combine(e00: torch.Tensor, e_image: torch.Tensor, e_both: torch.Tensor, s_image: float,
            s_text: float) -> torch.Tensor:
    """IP2P's guided prediction (Sec. 3.2.1) from the predictions without conditions (e00), with
    the image only (e_image) and with image and text (e_both)."""
    return e00 + s_image * (e_image - e00) + s_text * (e_both - e_image)


class GuidedModel(nn.Module):
    """A model whose prediction is the guided combination of three (`combine`), computed in one
    batch of 3B rows: (null image, no text), (image, no text), (image, text). It has the wrapped
    model's `cfg` and parameters, so the samplers (`sample.ddim`) take it as they take a model."""

    def __init__(self, model: nn.Module, s_image: float = IMAGE_SCALE, s_text: float = TEXT_SCALE):
        super().__init__()
        self.model = model
        self.cfg = model.cfg
        self.s_image, self.s_text = float(s_image), float(s_text)

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """x_t [B, C, h, w], t [B], cond [B, C', h, w] -> the guided prediction [B, C, h, w]."""
        b = x_t.shape[0]
        conds = torch.cat([null_condition(cond, self.cfg), cond, cond])
        text = torch.zeros(3 * b, dtype=torch.bool, device=x_t.device)
        text[2 * b:] = True
        out = self.model(torch.cat([x_t] * 3), torch.cat([t] * 3), conds, text=text)
        e00, e_image, e_both = out.chunk(3)
        return combine(e00, e_image, e_both, self.s_image, self.s_text)


# --------------------------------------------------------------------------- the pipeline's parts


class Unguided:
    """No guidance (Skyeyes, controlnet, gvg): training sees every condition and the prompt, the
    sampler calls the model itself. The guidance part of `pipeline.DiffusionMethod`."""

    def drop(self, cond: torch.Tensor, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Training conditions [B, C, h, w] as the model sees them, and the text mask [B] (None:
        the prompt everywhere)."""
        return cond, None

    def key(self) -> dict:
        """What else the ACM stage depends on (its cache key)."""
        return {}

    def sampling_model(self, model: nn.Module) -> nn.Module:
        """The model the sampler calls."""
        return model

    def labels(self) -> list[str]:
        """The guidance in words, for a run's list of components (none: no guidance)."""
        return []


class ImageTextGuidance(Unguided):
    """InstructPix2Pix's guidance on image and text: conditions dropped in training (`draw_drops`,
    `null_condition`), the guided combination at sampling (`GuidedModel`).

    Args:
        cfg: the model's core (its null image condition; it must diffuse the frames, not their
            residual from the condition, and have the unconditional text, `null_prompt`).
        drops: (p_image, p_text, p_both) of training.
        scales: (s_I, s_T) of sampling.
    """

    def __init__(self, cfg: CoreConfig, drops: tuple[float, float, float], scales: tuple[float, float]):
        if cfg.residual:
            raise ValueError("image guidance: a dropped image condition leaves no prior to add a residual to "
                             "(core.residual must be off)")
        if not cfg.null_prompt:
            raise ValueError("text guidance needs core.null_prompt (the unconditional embedding)")
        check_drops(*drops)
        self.cfg, self.drops, self.scales = cfg, tuple(drops), tuple(scales)

    def drop(self, cond: torch.Tensor, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(conditions with the dropped images null, text mask: False where the text is dropped)."""
        drop_image, drop_text = draw_drops(cond.shape[0], g, *self.drops)
        return null_condition(cond, self.cfg, drop_image), ~drop_text

    def key(self) -> dict:
        return {"drop": list(self.drops)}

    def sampling_model(self, model: nn.Module) -> nn.Module:
        return GuidedModel(model, *self.scales)

    def labels(self) -> list[str]:
        return [f"classifier-free guidance on image and text (scales {self.scales[0]:g}, {self.scales[1]:g})"]
