"""What the importers share: the plan they build (`PlannedScene`, `PlannedFrame`), the checks
of input fields and files, cutting capture tracks into lanes (`split_lanes`, `resample_step`),
and `write_plan`, which writes a plan through `DatasetWriter`.

Every importer works in two phases. *Plan*: read and check every input field and file header,
convert the poses, group frames into lanes (scenes) and sequences; any bad input raises a
one-line `UserError` naming the file, the field and what was expected, before anything is
written. *Write*: `DatasetWriter` (validate=True) fills a temporary folder and moves it into
place only when complete and valid. The source formats are documented in docs/formats.md.
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ... import fields, imagefiles, inputfiles, outputfiles
from ...errors import UserError
from ..layout import DATASET_FILE
from ..writer import DatasetWriter

_fail = fields.fail

#: What the importers (and `data synthtown --out`) write: --force replaces only an empty folder or
#: a dataset written earlier (a folder holding dataset.json), never SRC or a folder around it.
DATASET_OUTPUT = outputfiles.OutputKind("a dataset folder", folder=True, marker=DATASET_FILE)


def check_out(out: str | Path, force: bool, inputs, inputs_are: str = "the capture (SRC)") -> Path:
    """Refuse, before any work, an OUT that is, holds or lies inside an input (SRC, depth folders),
    or that exists without --force, or with it is not an earlier dataset (`outputfiles.check_output`)."""
    return outputfiles.check_output(out, force=force, kind=DATASET_OUTPUT, inputs=inputs, inputs_are=inputs_are)


@dataclass
class PlannedFrame:
    """One frame to write: where its pixels come from and its pose in our world."""

    kind: str  # "ground" | "aerial"
    image: Path
    c2w: np.ndarray  # [4, 4] OpenCV camera-to-world, metres, right-handed z-up world
    intrinsics: dict  # width, height, fx, fy, cx, cy
    depth: Callable[[], np.ndarray] | None = None  # lazily decoded [H, W] metres, inf = sky
    sequence: str | None = None
    index: int | None = None


@dataclass
class PlannedScene:
    name: str
    ground: list[PlannedFrame] = field(default_factory=list)
    aerial: list[PlannedFrame] = field(default_factory=list)
    meta: dict = field(default_factory=dict)


def yaw_sequence_name(offset_deg: float) -> str:
    """`yaw045` for a yaw offset of 45 deg (wrapped to [0, 360), rounded to whole degrees)."""
    return f"yaw{int(round(offset_deg)) % 360:03d}"


# --------------------------------------------------------------------------- field checks


def split_lanes(positions: np.ndarray, *, max_turn_deg: float = 30.0, gap_factor: float = 3.0) -> list[np.ndarray]:
    """Cut an ordered track of capture points [N, 3] into lanes: straight runs of regular steps.

    A lane ends where a step is longer than `gap_factor` times the median step (a jump to
    another street) or the direction of travel turns by more than `max_turn_deg` (a corner).
    Returns index arrays into `positions`, each of at least 2 points.
    """
    pts = np.asarray(positions, dtype=np.float64)
    assert pts.ndim == 2 and pts.shape[1] == 3, pts.shape  # [N, 3]
    if len(pts) < 2:
        return []
    steps = np.diff(pts[:, :2], axis=0)  # [N-1, 2], xy only: lanes are horizontal drives
    lengths = np.linalg.norm(steps, axis=1)
    median = float(np.median(lengths[lengths > 1e-6])) if np.any(lengths > 1e-6) else 0.0
    lanes, start = [], 0
    ref_dir = None
    for i, (s, n) in enumerate(zip(steps, lengths)):
        cut = n > gap_factor * median or n <= 1e-6
        if not cut and ref_dir is not None:
            cos = float(s @ ref_dir) / n
            cut = cos < math.cos(math.radians(max_turn_deg))
        if cut:
            if i + 1 - start >= 2:
                lanes.append(np.arange(start, i + 1))
            start, ref_dir = i + 1, None
        elif ref_dir is None:
            ref_dir = s / n
    if len(pts) - start >= 2:
        lanes.append(np.arange(start, len(pts)))
    return lanes


def resample_step(step_m: float, target_m: float, tol: float = 0.1) -> int | None:
    """Keep every k-th point so that k * step_m matches target_m within tol * target_m; None
    when no whole k does (e.g. 5 m captures for a 2 m protocol)."""
    if step_m <= 0:
        return None
    k = max(1, int(round(target_m / step_m)))
    return k if abs(k * step_m - target_m) <= tol * target_m else None


def rel_file(base: Path, where: str, value: Any, what: str, root: Path | None = None) -> Path:
    """A file named relative to `base` that stays inside `root` (default `base`) once '..' and
    symlinks are resolved, and is a regular file."""
    root = base if root is None else root
    if not isinstance(value, str) or not value or "\x00" in value:
        _fail(where, f"expected {what} (a path relative to {base}), got {value!r}")
    p = Path(os.path.normpath(base / value))
    if not inputfiles.inside(p, root):
        _fail(where, f"{what} {value!r} leaves {root} (through '..', an absolute path or a symlink)")
    if not p.is_file():
        _fail(where, f"{what} {p} not found" + (" (not a regular file)" if p.exists() else ""))
    return inputfiles.check_regular(p)


def check_size(path: Path, where: str, width: int, height: int) -> int:
    """Check an image's size from its header; returns its channel count."""
    w, h, c, _ = imagefiles.image_header(path)
    if (w, h) != (width, height):
        _fail(where, f"{path} is {w}x{h}, expected {width}x{height} (fields 'width', 'height')")
    return c


def town_split(town: str, protocol, split: str | None, flag: str = "--split") -> str:
    """The split of `town`: the protocol's, else `split` (the `flag` option), else an error."""
    if town in protocol.data.test:
        return "test"
    if town in protocol.data.train:
        return "train"
    if split:
        return split
    raise UserError(
        f"town {town!r} is in neither the train ({', '.join(protocol.data.train)}) nor the test "
        f"({', '.join(protocol.data.test)}) towns of protocol {protocol.ref}; pass {flag} train|test")


def _group_intrinsics(frames: list[PlannedFrame]) -> dict | None:
    """The most common intrinsics of a group; frames that differ carry their own."""
    if not frames:
        return None
    keys = [tuple(sorted(f.intrinsics.items())) for f in frames]
    best = max(set(keys), key=keys.count)
    return dict(best)


def check_sequences(scene: PlannedScene, where: str) -> None:
    """Every sequence of the scene is numbered 0..n-1."""
    seqs: dict[str, list[int]] = {}
    for f in scene.ground:
        seqs.setdefault(f.sequence, []).append(f.index)
    for name, idx in sorted(seqs.items()):
        if sorted(idx) != list(range(len(idx))):
            dup = sorted({i for i in idx if idx.count(i) > 1})
            gaps = fields.gaps(idx)
            what = f"duplicate index {dup[0]}" if dup else f"missing index {gaps[0]}"
            _fail(where, f"scene {scene.name!r} sequence {name!r} has {what} (field 'index' must run 0..n-1)")


# --------------------------------------------------------------------------- writing


def write_plan(out: Path, scenes: list[PlannedScene], *, name: str, protocol: str, splits: dict[str, list[str]],
               meta: dict, force: bool, progress: bool, inputs=(), inputs_are: str = "the capture (SRC)") -> Path:
    """Write planned scenes atomically; validates the result before moving it into place. `out`
    is checked against `inputs` (what the plan reads) before writing and again as it is moved in."""
    from tqdm import tqdm

    check_out(out, force, inputs, inputs_are)
    total = sum(len(s.ground) + len(s.aerial) for s in scenes)
    with outputfiles.reading(*inputs), \
            DatasetWriter(out, name=name, protocol=protocol, overwrite=force, validate=True) as w, \
            tqdm(total=total, desc=f"import {name}", unit="frame", file=sys.stderr,
                 disable=None if progress else True) as bar:
        for s in scenes:
            ground = sorted(s.ground, key=lambda f: (f.sequence, f.index))
            groups = {"ground": _group_intrinsics(ground), "aerial": _group_intrinsics(s.aerial)}
            groups = {k: v or groups["ground"] for k, v in groups.items()}
            sw = w.scene(s.name, groups, meta=s.meta)
            for f in [*s.aerial, *ground]:
                px = imagefiles.read_image_uint8(f.image)
                if px.shape[2] not in (3, 4):
                    raise UserError(f"{f.image}: expected an RGB image, got {px.shape[2]} channel(s)")
                extra = {} if f.intrinsics == groups[f.kind] else {"intrinsics": f.intrinsics}
                depth = f.depth() if f.depth is not None else None
                if f.kind == "ground":
                    sw.add_ground(px[..., :3], f.c2w, sequence=f.sequence, index=f.index, depth=depth, **extra)
                else:
                    sw.add_aerial(px[..., :3], f.c2w, depth=depth, **extra)
                bar.update(1)
            sw.close()
        w.finish(splits=splits, meta=meta)
    return out


def ordered_splits(scenes: list[PlannedScene], split_of: dict[str, str]) -> dict[str, list[str]]:
    """{"train": [...], "test": [...]} in the order of `scenes`."""
    out: dict[str, list[str]] = {"train": [], "test": []}
    for s in scenes:
        out.setdefault(split_of[s.name], []).append(s.name)
    return out

