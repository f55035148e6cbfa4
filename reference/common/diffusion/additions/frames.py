"""Small operations on a sequence's frames that the additions share."""

from __future__ import annotations

import numpy as np
import torch


def blur(a: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian low-pass of a [C, H, W] array over H and W (reflected at the border)."""
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(a, (0, sigma, sigma), mode="reflect")


def blur_frames(x: torch.Tensor, sigma: float) -> np.ndarray:
    """Frames [N, C, H, W] -> their Gaussian low-passes (`blur`, each frame on its own), float64."""
    return np.stack([blur(f, sigma) for f in x.detach().double().cpu().numpy()])


def blend(x: np.ndarray, target: np.ndarray, mask: np.ndarray, mix: float) -> np.ndarray:
    """A frame x [H, W, 3] moved `mix` of the way to target [H, W, 3] on mask [H, W] (bool), half
    of that on the mask's border pixels (those with a 3 x 3 neighbour outside it)."""
    from scipy.ndimage import uniform_filter

    m = mask.astype(np.float64)
    weight = mix * np.maximum(m * (uniform_filter(m, 3, mode="nearest") > 0.999), 0.5 * m)
    return x + weight[..., None] * (target - x)


def as_frames(out: np.ndarray, like: torch.Tensor) -> torch.Tensor:
    """Frames [N, H, W, 3] (numpy) -> [N, 3, H, W] on `like`'s device and dtype, in [0, 1]."""
    return torch.as_tensor(out.transpose(0, 3, 1, 2).copy(), device=like.device).to(like.dtype).clamp(0.0, 1.0)


def hwc(imgs: torch.Tensor) -> np.ndarray:
    """Frames [N, 3, H, W] -> float64 numpy [N, H, W, 3] on the CPU."""
    return imgs.detach().double().cpu().numpy().transpose(0, 2, 3, 1)
