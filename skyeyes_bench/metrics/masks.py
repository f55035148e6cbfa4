"""Mask cache: the seen masks of ground frames (`geometry.seen_mask`), computed once per content.

Like the feature cache (`metrics.cache`), an entry is keyed by what determines it and never
recomputed: the mask algorithm's version, the depth tolerance, the ground frame's depth file
sha256, pose and intrinsics, and a digest of every aerial view of its scene (depth file sha256,
pose, intrinsics). Entry: `<cache>/masks/<VERSION>/<key[:2]>/<key>.bits`, the mask's bits
(`np.packbits`, row-major) followed by their own sha256 (32 bytes), so a damaged entry is detected
and recomputed. Writes are atomic.

Warp masks are not cached: a warp tests each pixel against one other view (one projection per
pixel), cheaper than reading an entry back would be worth; the seen mask tests every aerial view.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from .. import paths
from ..inputfiles import sha256_file
from .cache import read_verified, write_verified

#: Bump when `geometry.seen_mask` changes what it computes: old entries are then never read.
VERSION = "visibility-1"

#: What the last call did: {"hits": n, "misses": n, "corrupt": n} (tests and progress output).
last_call: dict[str, int] = {"hits": 0, "misses": 0, "corrupt": 0}


def masks_dir() -> Path:
    return paths.cache_dir() / "masks" / VERSION


def _camera_text(frame) -> str:
    i = frame.intrinsics
    return (np.asarray(frame.c2w, "<f8").tobytes().hex() + " "
            + " ".join(repr(float(i[k])) for k in ("width", "height", "fx", "fy", "cx", "cy")))


def _read(path: Path, n_bits: int) -> np.ndarray | None:
    body = read_verified(path, (n_bits + 7) // 8, last_call)
    return None if body is None else np.unpackbits(np.frombuffer(body, np.uint8), count=n_bits).astype(bool)


def _write(path: Path, mask: np.ndarray) -> None:
    write_verified(path, np.packbits(mask.ravel()).tobytes())


def seen_masks(scene, frames: list, tol: float) -> np.ndarray:
    """Seen masks of ground `frames` of `scene` (a `data.layout.Scene`), from the cache where possible.

    Args:
        scene: the scene; its aerial frames and their depth layer are the views tested.
        frames: ground frames of the scene, all of one size, with a depth layer.
        tol: relative depth tolerance (`geometry.seen_mask`).

    Returns:
        bool [T, H, W] in the order of `frames`.
    """
    from .geometry import seen_mask

    last_call.update(hits=0, misses=0, corrupt=0)
    aerial_lines = [f"{sha256_file(a.layer_path('depth'))} {_camera_text(a)}\n" for a in scene.aerial]
    aerial_digest = hashlib.sha256("".join(aerial_lines).encode()).hexdigest()
    h, w = frames[0].height, frames[0].width
    out = np.zeros((len(frames), h, w), dtype=bool)
    aerial = None  # loaded on the first miss only
    for t, f in enumerate(frames):
        assert (f.height, f.width) == (h, w), "frames of one call share a size"
        key = hashlib.sha256(f"{VERSION}\n{tol!r}\n{sha256_file(f.layer_path('depth'))} {_camera_text(f)}\n"
                             f"{aerial_digest}".encode()).hexdigest()
        path = masks_dir() / key[:2] / f"{key}.bits"
        got = _read(path, h * w)
        if got is not None:
            out[t] = got.reshape(h, w)
            last_call["hits"] += 1
            continue
        if aerial is None:  # grouped by size: one stack of depths per image size
            aerial = {}
            for a in scene.aerial:
                aerial.setdefault((a.height, a.width), []).append(a)
            aerial = [([a.camera() for a in group], np.stack([a.depth() for a in group])) for group in aerial.values()]
        depth, cam = f.depth(), f.camera()
        for cams, depths in aerial:
            out[t] |= seen_mask(depth, cam, depths, cams, tol)
        _write(path, out[t])
        last_call["misses"] += 1
    return out
