"""Per-frame metrics on float [0, 1] sRGB images: PSNR, SSIM (Wang et al. 2004), LPIPS v0.1."""

from __future__ import annotations

import numpy as np


def _check_pair(pred: np.ndarray, gt: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    pred, gt = np.asarray(pred), np.asarray(gt)
    if pred.shape != gt.shape:
        raise ValueError(f"{name}: pred shape {pred.shape} != gt shape {gt.shape}")
    if pred.ndim < 3 or pred.shape[-1] != 3:
        raise ValueError(f"{name}: expected [..., H, W, 3], got {pred.shape}")
    return pred, gt


def psnr(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Peak signal-to-noise ratio in dB, 10 log10(1 / MSE), peak 1.

    Args:
        pred: float [..., H, W, 3] in [0, 1].
        gt: float [..., H, W, 3] in [0, 1].

    Returns:
        float64 [...]: one value per leading index; +inf where the images are identical
        (aggregates must handle it explicitly; see the protocol's `aggregate`).
    """
    pred, gt = _check_pair(pred, gt, "psnr")
    diff = pred.astype(np.float64) - gt.astype(np.float64)
    mse = np.mean(diff * diff, axis=(-3, -2, -1))
    with np.errstate(divide="ignore"):
        return -10.0 * np.log10(mse)  # mse 0 -> +inf, exactly and without a warning


def gaussian_window(window: int, sigma: float) -> np.ndarray:
    """Normalised 1-D Gaussian taps [window] (float64)."""
    r = (window - 1) / 2.0
    x = np.arange(window, dtype=np.float64) - r
    g = np.exp(-0.5 * (x / sigma) ** 2)
    return g / g.sum()


def _valid_filter(x: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """Separable 'valid' correlation over axes -3 (H) and -2 (W) of x [..., H, W, C].

    scipy's C correlate1d on the whole array, then the border where the window does not fit is
    cut off (its values, the only ones the padding mode touches, are discarded).
    """
    from scipy.ndimage import correlate1d

    r = len(taps) // 2
    h, w = x.shape[-3], x.shape[-2]
    out = correlate1d(x, taps, axis=x.ndim - 3, mode="constant")[..., r:h - r, :, :]
    return correlate1d(out, taps, axis=x.ndim - 2, mode="constant")[..., :, r:w - r, :]


def ssim(pred: np.ndarray, gt: np.ndarray, *, window: int = 11, sigma: float = 1.5,
         k1: float = 0.01, k2: float = 0.03) -> np.ndarray:
    """Structural similarity of Wang et al. (2004), data range 1, mean over pixels and channels.

    Gaussian window `window` x `window` with std `sigma`, population (biased) variances, the
    map evaluated where the window fits inside the image ('valid'), which is what
    `skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=1, channel_axis=-1)` averages over (it crops the
    border it padded).

    Args:
        pred: float [..., H, W, 3] in [0, 1], H and W >= window.
        gt: float [..., H, W, 3] in [0, 1].

    Returns:
        float64 [...].
    """
    return ssim_map(pred, gt, window=window, sigma=sigma, k1=k1, k2=k2).mean(axis=(-3, -2, -1))


def ssim_map(pred: np.ndarray, gt: np.ndarray, *, window: int = 11, sigma: float = 1.5,
             k1: float = 0.01, k2: float = 0.03) -> np.ndarray:
    """The SSIM map `ssim` averages: float64 [..., H - 2r, W - 2r, 3] for r = window // 2, where
    map pixel (i, j) is the window centred on image pixel (i + r, j + r)."""
    pred, gt = _check_pair(pred, gt, "ssim")
    if window % 2 != 1 or pred.shape[-3] < window or pred.shape[-2] < window:
        raise ValueError(f"ssim: odd window <= image size required (window {window}, image {pred.shape[-3:-1]})")
    x = pred.astype(np.float64)
    y = gt.astype(np.float64)
    taps = gaussian_window(window, sigma)
    mx, my, sxx, syy, sxy = _valid_filter(np.stack([x, y, x * x, y * y, x * y]), taps)
    vx = sxx - mx * mx
    vy = syy - my * my
    cxy = sxy - mx * my
    c1, c2 = (k1 * 1.0) ** 2, (k2 * 1.0) ** 2  # data range 1
    return ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))


def lpips(pred: np.ndarray, gt: np.ndarray, net: str = "alex", *, batch_size: int = 16,
          device=None) -> np.ndarray:
    """LPIPS v0.1 distance (Zhang et al. 2018), AlexNet or VGG16 backbone.

    Args:
        pred: float [..., H, W, 3] in [0, 1] (scaled to [-1, 1] inside, as `lpips` does with
            normalize=True).
        gt: float [..., H, W, 3] in [0, 1].
        net: "alex" or "vgg".
        batch_size: pairs per forward pass (bounds memory).
        device: torch device the network runs on (None: `extractors.on_device`'s, else the CPU).

    Returns:
        float64 [...].

    Raises:
        MetricUnavailable: the backbone or linear-head weights are missing.
    """
    return _lpips(pred, gt, net, batch_size, spatial=False, device=device)


def lpips_map(pred: np.ndarray, gt: np.ndarray, net: str = "alex", *, batch_size: int = 16,
              device=None) -> np.ndarray:
    """LPIPS v0.1 spatial map (`lpips.LPIPS(spatial=True)`): float64 [..., H, W] for inputs as `lpips`.

    Each layer's linear-head output upsampled (bilinear, align_corners=False) to the image size and
    summed over the 5 layers. Its mean is close to `lpips` (not equal: upsampling is not
    mean-preserving at the borders).

    Raises:
        MetricUnavailable: the backbone or linear-head weights are missing.
    """
    return _lpips(pred, gt, net, batch_size, spatial=True, device=device)


def _lpips(pred, gt, net: str, batch_size: int, *, spatial: bool, device=None) -> np.ndarray:
    from .extractors import get_extractor, pad_batch

    pred, gt = _check_pair(pred, gt, "lpips")
    if net not in ("alex", "vgg"):
        raise ValueError(f"lpips: net must be 'alex' or 'vgg', got {net!r}")
    ex = get_extractor(f"lpips-{net}-v0.1")
    run = ex.distance_map if spatial else ex.distance
    tail = pred.shape[-3:-1] if spatial else ()  # a map per pair, or a number
    lead = pred.shape[:-3]
    p = pred.reshape((-1,) + pred.shape[-3:])
    g = gt.reshape((-1,) + gt.shape[-3:])
    outs = []
    for i in range(0, len(p), batch_size):
        n = min(batch_size, len(p) - i)
        # no call below the network's `min_batch` pairs (`pad_batch`): a pair's value does not depend on its batch
        k = ex.min_batch
        outs.append(run(pad_batch(p[i:i + n], k), pad_batch(g[i:i + n], k), device=device)[:n])
    out = np.concatenate(outs) if outs else np.zeros((0,) + tail)
    return out.reshape(lead + tail)
