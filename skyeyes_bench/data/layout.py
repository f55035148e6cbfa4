"""Read, validate and write the canonical dataset layout.

```
<root>/dataset.json   {"name", "protocol": "<id>@<N>", "splits": {"train": [...], "test": [...]},
                       "scenes": [...], "meta": {...}}
<root>/<scene>/scene.json
    {"intrinsics": {"ground": {width, height, fx, fy, cx, cy}, "aerial": {...}},
     "aerial": [{"file", "c2w"}...],
     "ground": [{"file", "c2w", "sequence", "index"}...], "meta": {...}}
<root>/<scene>/aerial/*.png, ground/*.png          8-bit sRGB
<root>/<scene>/ground_depth/*.exr, aerial_depth/   float32 metres, same stem as the image
<root>/<scene>/ground_semantics/*.png, aerial_semantics/   8-bit labels
```

A scene is one lane; a sequence is the ordered ground frames of one lane at one yaw offset.
A frame may carry its own "intrinsics" (same keys) overriding its group's.

This module reads and validates; `skyeyes_bench.data.writer` writes (`DatasetWriter`);
`skyeyes_bench.data.layers` names, checks and reads the layer files.
"""

from __future__ import annotations

import os
import re
import sys
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from .. import fields, imagefiles, inputfiles
from ..cameras import Camera, K_from_dict, rigid_problem
from ..errors import UserError, ValidationError
from .layers import LAYERS, layer_file, layer_header, read_layer  # noqa: F401  (importable from here too)

DATASET_FILE = "dataset.json"
SCENE_FILE = "scene.json"
KINDS = ("ground", "aerial")
_INTRINSIC_KEYS = ("width", "height", "fx", "fy", "cx", "cy")
#: Largest image side accepted in intrinsics (the decoders' pixel limit is imagefiles.MAX_PIXELS).
_MAX_SIDE = 65536
_PROTOCOL_REF = re.compile(r"^[a-z0-9][a-z0-9._-]*@[1-9]\d*$")


@dataclass(frozen=True, eq=False)
class Frame:
    """One posed image. Pixels load lazily (`image()`, `depth()`, `semantics()`)."""

    scene_root: Path
    kind: str  # "ground" | "aerial"
    file: str  # relative to the scene folder
    c2w: np.ndarray  # [4, 4]
    intrinsics: dict  # width, height, fx, fy, cx, cy
    sequence: str | None = None
    index: int | None = None

    @property
    def path(self) -> Path:
        return self.scene_root / self.file

    @property
    def stem(self) -> str:
        return Path(self.file).stem

    @property
    def width(self) -> int:
        return int(self.intrinsics["width"])

    @property
    def height(self) -> int:
        return int(self.intrinsics["height"])

    def camera(self) -> Camera:
        return Camera(K_from_dict(self.intrinsics), self.c2w, self.width, self.height)

    def image(self) -> np.ndarray:
        """float32 [H, W, 3] in [0, 1]."""
        return imagefiles.read_image(self.path)

    def layer_path(self, layer: str) -> Path:
        return self.scene_root / layer_file(self.file, layer)

    def depth(self) -> np.ndarray | None:
        """float32 [H, W] planar depth in metres (inf = sky), or None if the layer is absent."""
        p = self.layer_path("depth")
        return read_layer(p, "depth") if p.exists() else None

    def semantics(self) -> np.ndarray | None:
        """uint8 [H, W] labels, or None if the layer is absent."""
        p = self.layer_path("semantics")
        return read_layer(p, "semantics") if p.exists() else None


@dataclass(frozen=True, eq=False)
class Sequence:
    """The ordered ground frames of one lane at one yaw offset."""

    scene: str
    name: str
    frames: tuple[Frame, ...]

    @property
    def id(self) -> str:
        return f"{self.scene}/{self.name}"

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self) -> Iterator[Frame]:
        return iter(self.frames)


@dataclass(frozen=True, eq=False)
class Scene:
    name: str
    root: Path
    aerial: tuple[Frame, ...]
    ground: tuple[Frame, ...]
    meta: dict = field(default_factory=dict)

    @cached_property
    def sequences(self) -> dict[str, Sequence]:
        groups: dict[str, list[Frame]] = {}
        for f in self.ground:
            groups.setdefault(str(f.sequence), []).append(f)
        return {
            name: Sequence(self.name, name, tuple(sorted(fs, key=lambda f: int(f.index or 0))))
            for name, fs in sorted(groups.items())
        }

    def layers(self) -> dict[str, bool]:
        """Which optional layers exist, e.g. {"ground_depth": True, "aerial_semantics": False}."""
        return {f"{k}_{layer}": (self.root / f"{k}_{layer}").is_dir() for k in KINDS for layer in LAYERS}


@dataclass(frozen=True, eq=False)
class Dataset:
    root: Path
    name: str
    protocol: str  # "<id>@<N>"
    splits: dict[str, tuple[str, ...]]
    scenes: dict[str, Scene]
    meta: dict = field(default_factory=dict)
    # The split its "test" scenes stand for: "test", or "val" in the view of a run on the
    # validation split (`splits.scored_view`: "train" and "test" are then what that run fits and scores).
    scored: str = "test"

    def split(self, name: str) -> list[Scene]:
        if name not in self.splits:
            raise UserError(f"{self.root / DATASET_FILE}: no split {name!r} (splits: {', '.join(self.splits)})")
        return [self.scenes[s] for s in self.splits[name]]

    def sequences(self, split: str) -> list[Sequence]:
        return [seq for scene in self.split(split) for seq in scene.sequences.values()]

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name, "protocol": self.protocol, "root": str(self.root), "splits": {}}
        for split, names in self.splits.items():
            scenes = [self.scenes[n] for n in names]
            out["splits"][split] = {
                "scenes": len(scenes),
                "sequences": sum(len(s.sequences) for s in scenes),
                "ground_frames": sum(len(s.ground) for s in scenes),
                "aerial_frames": sum(len(s.aerial) for s in scenes),
            }
        sizes = {(f.kind, f.width, f.height) for s in self.scenes.values() for f in (*s.ground, *s.aerial)}
        out["resolution"] = {k: ", ".join(f"{w}x{h}" for kk, w, h in sorted(sizes) if kk == k)
                             for k in sorted({k for k, _, _ in sizes})}
        lengths = [len(q) for s in self.scenes.values() for q in s.sequences.values()]
        out["sequence_length"] = {"min": min(lengths), "max": max(lengths)} if lengths else {}
        layers: dict[str, bool] = {}
        for s in self.scenes.values():
            for k, v in s.layers().items():
                layers[k] = layers.get(k, True) and v
        out["layers"] = layers
        return out


# --------------------------------------------------------------------------- reading


def _intrinsics_problem(d: Any, where: str) -> str | None:
    if not isinstance(d, dict):
        return f"{where}: expected a table with {', '.join(_INTRINSIC_KEYS)}"
    missing = [k for k in _INTRINSIC_KEYS if k not in d]
    if missing:
        return f"{where}: missing {', '.join(missing)}"
    bad = [k for k in _INTRINSIC_KEYS if not fields.is_number(d[k])]
    if bad:
        return f"{where}: {', '.join(bad)} must be finite numbers, got {', '.join(repr(d[k]) for k in bad)}"
    w, h, fx, fy, cx, cy = (float(d[k]) for k in _INTRINSIC_KEYS)
    if not (1 <= w <= _MAX_SIDE and 1 <= h <= _MAX_SIDE) or w != int(w) or h != int(h):
        return f"{where}: width/height must be integers in 1..{_MAX_SIDE}, got {d['width']}x{d['height']}"
    if not (fx > 0 and fy > 0 and np.isfinite(fx) and np.isfinite(fy)):
        return f"{where}: focal lengths must be positive, got fx={fx}, fy={fy}"
    if not (0 < cx < w and 0 < cy < h):
        return f"{where}: principal point ({cx}, {cy}) lies outside the {int(w)}x{int(h)} image"
    return None


def _escapes(path: Path, root: Path) -> str | None:
    """Why `path` is not inside the dataset `root` once symlinks are resolved, or None if it is:
    the README promises that a dataset's files stay inside its folder."""
    if inputfiles.inside(path, root):
        return None
    return f"{path}: leaves the dataset folder {root} (a symlink to {os.path.realpath(path)}); files stay inside it"


def _load_scene(root: Path, name: str, problems: list[str], check_files: bool,
                check_pixels: bool = False) -> Scene | None:
    sdir = root / name
    sfile = sdir / SCENE_FILE
    if (sdir.exists() or sdir.is_symlink()) and (why := _escapes(sdir, root)):
        problems.append(why)
        return None
    outside = _link_check(root, problems)
    raw = _read_scene_json(sfile, name, root, problems)
    if raw is None:
        return None
    intr = raw["intrinsics"]
    frames: dict[str, list[Frame]] = {k: [] for k in KINDS}
    seen_files: dict[str, int] = {}
    rejected_seqs: set[str] = set()
    unknown_seq_rejected = False  # a rejected frame whose sequence is unknown: any hole may be its
    group_rejected = False
    linked_out = False  # a frame refused for leaving the dataset: reported already
    for kind in KINDS:
        group = intr.get(kind)
        p = _intrinsics_problem(group, f"{sfile}: field 'intrinsics.{kind}'")
        if p:
            problems.append(p)
            group_rejected = group_rejected or kind == "ground"
            continue
        entries = raw.get(kind)
        if not isinstance(entries, list):
            problems.append(f"{sfile}: field '{kind}' must be a list of frames")
            continue
        accepted: set[int] = set()
        for i, e in enumerate(entries):
            frame = _frame_entry(sdir, sfile, kind, i, e, group, seen_files, problems)
            if frame is None:
                continue
            if outside(frame.path) or any(outside(frame.layer_path(layer)) for layer in LAYERS):
                linked_out = True
                continue
            if check_files:
                _check_frame_files(frame, problems, check_pixels)
            frames[kind].append(frame)
            accepted.add(i)
        if kind == "ground":  # a rejected frame leaves a hole in its sequence: reported already
            rejected = [e for i, e in enumerate(entries) if i not in accepted]
            rejected_seqs.update(str(e.get("sequence")) for e in rejected if isinstance(e, dict))
            unknown_seq_rejected = unknown_seq_rejected or any(
                not isinstance(e, dict) or not isinstance(e.get("sequence"), str) or not fields.NAME.match(e["sequence"])
                for e in rejected)
    meta = raw.get("meta", {})
    if meta is None:
        meta = {}
    if not isinstance(meta, dict):
        problems.append(f"{sfile}: field 'meta' must be an object")
        meta = {}
    scene = Scene(name, sdir, tuple(frames["aerial"]), tuple(frames["ground"]), meta)
    _check_numbering(scene, sfile, rejected_seqs, unknown_seq_rejected, problems)
    if not scene.ground and not group_rejected and not linked_out:  # rejected intrinsics or links: reported
        problems.append(f"{sfile}: scene has no ground frames")
    return scene


def _link_check(root: Path, problems: list[str]):
    """A function of a file path: True (reported in `problems`) if the file, or its folder, is linked
    out of the dataset `root`; a folder is resolved and reported once."""
    folders: dict[Path, str | None] = {}  # folder -> why it leaves the dataset, "" if absent (resolved once)

    def outside(p: Path) -> bool:
        """Report (once per folder) a file whose folder, or which itself, is linked out of the dataset."""
        folder = p.parent
        if folder not in folders:
            folders[folder] = _escapes(folder, root) if folder.exists() or folder.is_symlink() else ""
            if folders[folder]:
                problems.append(folders[folder])
        if folders[folder] is not None:  # linked out (reported), or absent (nothing to read there)
            return bool(folders[folder])
        if p.is_symlink() and (why := _escapes(p, root)):
            problems.append(why)
            return True
        return False

    return outside


def _read_scene_json(sfile: Path, name: str, root: Path, problems: list[str]) -> dict | None:
    """A scene's scene.json, or None after reporting why it is unusable (missing, unreadable, not an
    object, no 'intrinsics' table)."""
    if not sfile.is_file():
        problems.append(f"{sfile}: missing (scene {name!r} is listed in {DATASET_FILE})")
        return None
    try:
        raw = inputfiles.read_json(sfile, root=root)  # never a file linked from outside the dataset
    except UserError as e:
        problems.append(str(e))
        return None
    if not isinstance(raw, dict):
        problems.append(f"{sfile}: expected a JSON object")
        return None
    intr = raw.get("intrinsics")
    if not isinstance(intr, dict):
        problems.append(f"{sfile}: field 'intrinsics' missing (expected {{'ground': {{...}}, 'aerial': {{...}}}})")
        return None
    return raw


def _frame_entry(sdir: Path, sfile: Path, kind: str, i: int, e: Any, group: dict, seen_files: dict[str, int],
                 problems: list[str]) -> Frame | None:
    """The Frame of entry `e`, `kind`[i] of scene.json (group intrinsics `group`), or None after
    reporting why it is refused. `seen_files`: the scene's files so far -> entry index (updated)."""
    where = f"{sfile}: {kind}[{i}]"
    if not isinstance(e, dict) or not isinstance(e.get("file"), str):
        problems.append(f"{where}: expected an object with 'file' and 'c2w'")
        return None
    try:
        fields.rel_path(f"{where} field 'file'", e["file"], "the image file within the scene folder")
    except UserError as err:
        problems.append(str(err))
        return None
    where = f"{sfile}: {kind}[{i}] ({e['file']})"
    if e["file"] in seen_files:
        problems.append(f"{where}: field 'file' repeats {kind}[{seen_files[e['file']]}]'s file")
        return None
    seen_files[e["file"]] = i
    fi = e.get("intrinsics", group)
    if "intrinsics" in e and (p := _intrinsics_problem(fi, f"{where} field 'intrinsics'")):
        problems.append(p)
        return None
    if "c2w" not in e:
        problems.append(f"{where}: field 'c2w' missing (expected a 4x4 camera-to-world matrix)")
        return None
    try:
        c2w = fields.matrix(f"{where}: field 'c2w'", e["c2w"], 4, 4, "a camera-to-world matrix")
    except UserError as err:
        problems.append(str(err))
        return None
    if p := rigid_problem(c2w):
        problems.append(f"{where}: field 'c2w' is not a rigid transform: {p}")
        return None
    seq, idx = e.get("sequence"), e.get("index")
    if kind == "ground":
        try:
            fields.name(f"{where}: field 'sequence'", seq, "a sequence name")
            # an index past the frame count is reported as a gap, which is bounded by the
            # frames (not by the index: 10**12 once made a set of 10**12 numbers)
            fields.integer(f"{where}: field 'index'", idx, "the frame's position in its sequence")
        except UserError as err:
            problems.append(str(err))
            return None
    return Frame(sdir, kind, e["file"], c2w, dict(fi), seq, idx)


def _check_numbering(scene: Scene, sfile: Path, rejected_seqs: set[str], unknown_seq_rejected: bool,
                     problems: list[str]) -> None:
    """Report sequences not numbered 0..n-1, except those with a rejected frame (a hole reported
    already; any sequence's, when a rejected frame's sequence is unknown)."""
    for seq in scene.sequences.values():
        if seq.name in rejected_seqs or unknown_seq_rejected:
            continue
        idx = [f.index for f in seq.frames]
        if idx != list(range(len(idx))):
            dup = sorted({i for i in idx if idx.count(i) > 1})
            gaps = fields.gaps(idx)
            what = "; ".join(w for w in (f"duplicate indices {dup[:5]}" if dup else "",
                                         f"missing indices {gaps[:5]}" if gaps else "") if w)
            problems.append(f"{sfile}: sequence {seq.name!r} is not numbered 0..n-1 ({what}; field 'index')")


def _check_frame_files(frame: Frame, problems: list[str], check_pixels: bool = False) -> None:
    if not frame.path.is_file():
        problems.append(f"{frame.path}: missing file")
        return
    try:
        w, h, c, _ = imagefiles.image_header(frame.path)
        if check_pixels:  # a truncated PNG has an intact header; only decoding finds it
            imagefiles.read_image_uint8(frame.path)
    except UserError as e:
        problems.append(str(e))
        return
    if (w, h) != (frame.width, frame.height):
        problems.append(f"{frame.path}: image is {w}x{h}, intrinsics say {frame.width}x{frame.height}")
    if c not in (3, 4):
        problems.append(f"{frame.path}: expected an RGB image, got {c} channel(s)")
    for layer in LAYERS:
        lp = frame.layer_path(layer)
        if lp.parent.is_dir():
            if not lp.is_file():
                problems.append(f"{lp}: missing ({lp.parent.name}/ exists, so every {frame.kind} frame needs one)")
                continue
            try:
                lw, lh = layer_header(lp, layer)
                if check_pixels:
                    read_layer(lp, layer)
            except UserError as e:
                problems.append(str(e))
                continue
            if (lw, lh) != (w, h):
                problems.append(f"{lp}: {layer} is {lw}x{lh}, its image is {w}x{h}")


def validate_dataset(root: str | os.PathLike, *, check_files: bool = True, check_pixels: bool = False,
                     progress: bool = False) -> tuple[Dataset | None, list[str]]:
    """Read a dataset and collect every problem (no exception for bad data).

    Args:
        check_files: check that every image exists and its header matches the intrinsics.
        check_pixels: also decode every image and layer (finds truncated files; slow).
        progress: show a progress bar over scenes (stderr).
    """
    root = Path(root)
    problems: list[str] = []
    dfile = root / DATASET_FILE
    if not root.is_dir():
        return None, [f"{root}: not a folder"]
    if not dfile.is_file():
        return None, [f"{dfile}: missing (not a dataset folder; expected the canonical layout of docs/formats.md)"]
    try:
        raw = inputfiles.read_json(dfile, root=root)
    except UserError as e:
        return None, [str(e)]
    if not isinstance(raw, dict):
        return None, [f"{dfile}: expected a JSON object"]
    for key, typ in (("name", str), ("protocol", str), ("splits", dict), ("scenes", list)):
        if not isinstance(raw.get(key), typ):
            problems.append(f"{dfile}: field '{key}' missing or not a {typ.__name__}")
    if problems:
        return None, problems
    if not _PROTOCOL_REF.match(raw["protocol"]):
        problems.append(f"{dfile}: field 'protocol' is {raw['protocol']!r}, expected '<id>@<N>' (e.g. 'synthtown@1')")
    names = raw["scenes"]
    bad_names = []
    for i, n in enumerate(names):
        try:  # scene names become folder names: '..', '/' or a NUL would leave the dataset
            fields.name(f"{dfile}: field 'scenes[{i}]'", n, "a scene folder name")
        except UserError as err:
            bad_names.append(str(err))
    if bad_names:
        return None, problems + bad_names
    if len(set(names)) != len(names):
        return None, [f"{dfile}: field 'scenes' must list unique scene folder names"]
    splits: dict[str, tuple[str, ...]] = {}
    for split, members in raw["splits"].items():
        if not isinstance(members, list) or not all(isinstance(m, str) for m in members):
            problems.append(f"{dfile}: field 'splits.{split}' must be a list of scene names")
            continue
        for m in members:
            if m not in names:
                problems.append(f"{dfile}: split {split!r} names unknown scene {m!r} (field 'splits.{split}')")
        for m in sorted({m for m in members if members.count(m) > 1}):
            problems.append(f"{dfile}: split {split!r} lists scene {m!r} more than once (field 'splits.{split}')")
        for other, taken in splits.items():
            for m in sorted(set(members) & set(taken)):
                problems.append(f"{dfile}: scene {m!r} is in both split {other!r} and split {split!r}")
        splits[split] = tuple(dict.fromkeys(m for m in members if m in names))
    scenes = {}
    from tqdm import tqdm

    for n in tqdm(names, desc=f"check {root.name}", unit="scene", file=sys.stderr, disable=None if progress else True):
        s = _load_scene(root, n, problems, check_files, check_pixels)
        if s is not None:
            scenes[n] = s
    if problems:
        return None, problems
    ds = Dataset(root, raw["name"], raw["protocol"], splits, scenes, raw.get("meta", {}) or {})
    return ds, []


def open_dataset(root: str | os.PathLike, *, check_files: bool = True, check_pixels: bool = False,
                 progress: bool = False) -> Dataset:
    """Open and validate a dataset; raises ValidationError listing every problem."""
    ds, problems = validate_dataset(root, check_files=check_files, check_pixels=check_pixels, progress=progress)
    if problems:
        raise ValidationError(f"dataset {root}", problems)
    assert ds is not None
    return ds
