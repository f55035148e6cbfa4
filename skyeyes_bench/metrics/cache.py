"""Feature cache: features of image files and clips, keyed by content, never recomputed.

Key: (extractor id, weights sha256, device type, content sha256); the weight files are verified
(memoised sha256) before any entry is read, so entries are only ever reused with the weights they
came from, where the content sha256 is the file's sha256 for an image and, for a clip, the sha256
of its ordered member file sha256s. An entry is
`<features_dir>/<extractor id>/<weights sha256[:16]>[-<device type>]/<key[:2]>/<key>.f64` (no
suffix for the CPU, the reference: caches written before devices existed stay valid): the float64
little-endian feature bytes followed by their own sha256 (32 bytes), so a truncated or corrupted
entry is detected on read and recomputed. Writes are atomic.

The device is part of the key because GPU features agree with the CPU's only to float rounding:
a CPU evaluation must never be served features a GPU computed (its scores would no longer be
the reference bytes), and the other way round.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from .. import paths
from ..imagefiles import read_image
from ..inputfiles import sha256_file
from ..metricspec import CLIP_EXTRACTOR, IMAGE_EXTRACTOR
from ..outputfiles import atomic_path
from .extractors import current_device, get_extractor

#: What the last call did: {"hits": n, "misses": n, "corrupt": n} (tests and progress output).
last_call: dict[str, int] = {"hits": 0, "misses": 0, "corrupt": 0}


def _entry_dir(ex, device_type: str = "cpu") -> Path:
    wsha = ex.weights_sha256 or "noweights"
    return paths.features_dir() / ex.id / (wsha[:16] + ("" if device_type == "cpu" else f"-{device_type}"))


def _entry(ex, key: str, device_type: str = "cpu") -> Path:
    return _entry_dir(ex, device_type) / key[:2] / f"{key}.f64"


def read_verified(path: Path, size: int, counts: dict[str, int]) -> bytes | None:
    """The `size` bytes of a cache entry written by `write_verified`, or None if it is absent or
    damaged (wrong length or sha256; then `counts["corrupt"]` goes up and the caller recomputes)."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return None
    body, tail = data[:-32], data[-32:]
    if len(data) != size + 32 or hashlib.sha256(body).digest() != tail:
        counts["corrupt"] += 1
        return None
    return body


def write_verified(path: Path, body: bytes) -> None:
    """Write a cache entry atomically: `body` followed by its sha256 (32 bytes)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(body + hashlib.sha256(body).digest())


def _read_entry(path: Path, dim: int) -> np.ndarray | None:
    """The cached feature [dim], or None if absent or corrupted."""
    body = read_verified(path, dim * 8, last_call)
    return None if body is None else np.frombuffer(body, dtype="<f8").astype(np.float64)


def _write_entry(path: Path, feat: np.ndarray) -> None:
    write_verified(path, np.ascontiguousarray(feat, dtype="<f8").tobytes())


def _extract(extractor_id: str, keys: list[str], load, batch_size: int, progress: bool, unit: str,
             device=None) -> np.ndarray:
    ex = get_extractor(extractor_id)
    dev = current_device(device)
    # Cached features are reused only with verified weights: a deleted or altered weight file
    # makes the metric unavailable (with the fixing command) even when every feature is cached.
    ex.require()
    last_call.update(hits=0, misses=0, corrupt=0)
    out = np.zeros((len(keys), ex.dim), np.float64)
    todo = []
    for i, k in enumerate(keys):
        f = _read_entry(_entry(ex, k, dev.type), ex.dim)
        if f is None:
            todo.append(i)
        else:
            out[i] = f
    last_call["hits"] = len(keys) - len(todo)
    last_call["misses"] = len(todo)
    if not todo:
        return out
    from tqdm import tqdm

    done: dict[str, np.ndarray] = {}
    uniq, seen = [], set()  # the same content twice in one call is extracted once
    for i in todo:
        if keys[i] not in seen:
            seen.add(keys[i])
            uniq.append(i)
    bar = tqdm(total=len(uniq), desc=f"{ex.id} features", unit=unit, disable=None if progress else True, leave=False)
    for s in range(0, len(uniq), batch_size):
        idx = uniq[s:s + batch_size]
        items = [load(i) for i in idx]
        by_shape: dict[tuple, list[int]] = {}  # frames of different sizes go through separately
        for j, a in enumerate(items):
            by_shape.setdefault(a.shape, []).append(j)
        for group in by_shape.values():
            feats = ex.features(np.stack([items[j] for j in group]), device=dev)
            for j, f in zip(group, feats):
                done[keys[idx[j]]] = f
                _write_entry(_entry(ex, keys[idx[j]], dev.type), f)
        bar.update(len(idx))
    bar.close()
    for i in todo:
        out[i] = done[keys[i]]
    return out


def extract_image_features(extractor_id: str, paths_: list[Path], *, batch_size: int = 32,
                           progress: bool = True, device=None) -> np.ndarray:
    """Features of image files, from the cache where possible.

    Args:
        extractor_id: an image extractor id (e.g. "inception-tf-2015").
        paths_: image files (8-bit PNG); all must have the same size within a batch.
        device: torch device the network runs on (None: `extractors.on_device`'s, else the CPU);
            its type is part of the cache key.

    Returns:
        float64 [N, D] in the order of `paths_`.
    """
    ex = get_extractor(extractor_id)
    if ex.kind != IMAGE_EXTRACTOR:
        raise ValueError(f"{extractor_id} is a {ex.kind} extractor, not an image one")
    paths_ = [Path(p) for p in paths_]
    keys = [sha256_file(p) for p in paths_]
    return _extract(extractor_id, keys, lambda i: read_image(paths_[i]), batch_size, progress, "frame", device)


def extract_clip_features(extractor_id: str, clips: list[list[Path]], *, batch_size: int = 4,
                          progress: bool = True, device=None) -> np.ndarray:
    """Features of clips (ordered lists of frame files), from the cache where possible
    (`device` as in `extract_image_features`).

    Returns:
        float64 [M, D] in the order of `clips`.
    """
    ex = get_extractor(extractor_id)
    if ex.kind != CLIP_EXTRACTOR:
        raise ValueError(f"{extractor_id} is a {ex.kind} extractor, not a video one")
    clips = [[Path(p) for p in c] for c in clips]
    memo: dict[Path, str] = {}

    def sha(p: Path) -> str:
        if p not in memo:
            memo[p] = sha256_file(p)
        return memo[p]

    keys = [hashlib.sha256("\n".join(sha(p) for p in c).encode()).hexdigest() for c in clips]
    return _extract(extractor_id, keys, lambda i: np.stack([read_image(p) for p in clips[i]]),
                    batch_size, progress, "clip", device)
