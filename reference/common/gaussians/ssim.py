"""Differentiable SSIM (Wang et al. 2004) in torch, for the D-SSIM training loss.

Gaussian window 11x11, sigma 1.5, K1 0.01, K2 0.03, population (biased) covariance, 'valid'
windows only (the border is cropped as scikit-image does), mean over channels and pixels.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

# NOTE: constants of Wang et al. 2004 (IEEE TIP 13(4)), also protocol synthtown@1 [metrics.ssim].
WINDOW, SIGMA, K1, K2 = 11, 1.5, 0.01, 0.03


def _window(dtype, device) -> torch.Tensor:
    x = torch.arange(WINDOW, dtype=dtype, device=device) - (WINDOW - 1) / 2
    g = torch.exp(-(x * x) / (2 * SIGMA * SIGMA))
    g = g / g.sum()
    return g


def ssim_map(a: torch.Tensor, b: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """Per-pixel SSIM [C, H-10, W-10] of images a, b [H, W, C]."""
    assert a.shape == b.shape and a.ndim == 3, (a.shape, b.shape)
    c = a.shape[2]
    x = torch.stack([a, b, a * a, b * b, a * b]).permute(0, 3, 1, 2).reshape(1, 5 * c, *a.shape[:2])
    g = _window(a.dtype, a.device)
    x = F.conv2d(x, g.view(1, 1, 1, -1).repeat(5 * c, 1, 1, 1), groups=5 * c)  # separable: rows
    x = F.conv2d(x, g.view(1, 1, -1, 1).repeat(5 * c, 1, 1, 1), groups=5 * c)  # then columns
    mu_a, mu_b, aa, bb, ab = x.reshape(5, c, *x.shape[2:])
    var_a, var_b, cov = aa - mu_a * mu_a, bb - mu_b * mu_b, ab - mu_a * mu_b
    c1, c2 = (K1 * data_range) ** 2, (K2 * data_range) ** 2
    return ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a * mu_a + mu_b * mu_b + c1) * (var_a + var_b + c2))


def ssim(a: torch.Tensor, b: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """Mean SSIM of a, b [H, W, C] (scalar)."""
    return ssim_map(a, b, data_range).mean()
