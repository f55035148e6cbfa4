"""Per-frame metrics restricted to a pixel region (the seen / unseen parts of a ground view).

Each function returns the frame's value on its region and the region's pixel count, the weight
with which results pool frames (docs/metrics.md): an empty region gives (NaN, 0).
"""

from __future__ import annotations

import numpy as np

from . import image


def _check(pred: np.ndarray, gt: np.ndarray, masks: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    pred, gt = np.asarray(pred), np.asarray(gt)
    masks = np.asarray(masks, dtype=bool)
    if pred.shape != gt.shape or pred.ndim != 4 or pred.shape[-1] != 3 or masks.shape != pred.shape[:3]:
        raise ValueError(f"{name}: expected pred, gt [B, H, W, 3] and masks [B, H, W], got {pred.shape}, "
                         f"{gt.shape}, {masks.shape}")
    return pred, gt


def masked_mean(maps: np.ndarray, masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean of maps [B, H, W] over masks [B, H, W] -> (float64 [B], NaN where empty; int64 [B] counts)."""
    maps = np.asarray(maps, dtype=np.float64)
    masks = np.asarray(masks, dtype=bool)
    assert maps.shape == masks.shape and maps.ndim == 3, (maps.shape, masks.shape)
    n = masks.sum(axis=(1, 2))
    total = np.where(masks, maps, 0.0).sum(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, total / np.maximum(n, 1), np.nan), n.astype(np.int64)


def psnr(pred: np.ndarray, gt: np.ndarray, masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """PSNR on the region: 10 log10(1 / MSE) with the MSE over the region's pixels and the 3
    channels (+inf if they match exactly).

    Args:
        pred, gt: float [B, H, W, 3] in [0, 1]; masks: bool [B, H, W].

    Returns:
        float64 [B] (NaN where the region is empty), int64 [B] pixel counts.
    """
    pred, gt = _check(pred, gt, masks, "psnr")
    diff = pred.astype(np.float64) - gt.astype(np.float64)
    mse, n = masked_mean((diff * diff).mean(axis=-1), masks)
    with np.errstate(divide="ignore", invalid="ignore"):
        return -10.0 * np.log10(mse), n


def ssim(pred: np.ndarray, gt: np.ndarray, masks: np.ndarray, **settings) -> tuple[np.ndarray, np.ndarray]:
    """Mean of the SSIM map (`image.ssim_map`, channel mean) over the region's pixels that are
    window centres (the map covers pixels r .. H-1-r, r = window // 2: the border is left out as
    `image.ssim` leaves it out).

    Returns:
        float64 [B] (NaN where the region has no window centre), int64 [B] centre counts.
    """
    pred, gt = _check(pred, gt, masks, "ssim")
    return map_mean(image.ssim_map(pred, gt, **settings).mean(axis=-1), masks)


def map_mean(maps: np.ndarray, masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`masked_mean` of maps [B, h, w] that cover the centre of the masks [B, H, W] (a 'valid'
    map such as SSIM's leaves out (H - h) / 2 pixels on each side): the masks are cropped alike."""
    r, c = (masks.shape[1] - maps.shape[1]) // 2, (masks.shape[2] - maps.shape[2]) // 2
    return masked_mean(maps, np.asarray(masks, bool)[:, r:r + maps.shape[1], c:c + maps.shape[2]])
