"""Importers: CARLA capture folders and MatrixCity / CitySample captures -> canonical layout.

Both work in two phases. *Plan*: read and check every input field and file header, convert the
poses, group frames into lanes (scenes) and sequences; any bad input raises a one-line
`UserError` naming the file, the field and what was expected, before anything is written.
*Write*: `DatasetWriter` (validate=True) fills a temporary folder and moves it into place only
when complete and valid. The source formats are documented in docs/formats.md.
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .. import fields, fileio
from ..cameras import from_carla, from_matrixcity, intrinsics
from ..errors import UserError
from .layout import DatasetWriter


#: CARLA depth camera: 24-bit code over 3 channels, far plane at 1000 m.
#: NOTE: CARLA docs, "Sensors reference / Depth camera": normalized = (R + G*256 + B*256^2)
#: / (256^3 - 1); in metres = 1000 * normalized.
CARLA_DEPTH_FAR_M = 1000.0
_CARLA_DEPTH_MAX_CODE = 256**3 - 1

#: MatrixCity depth EXRs are float16 centimetres; the float16 maximum marks sky / invalid.
#: NOTE: MatrixCity scripts/rgbd2pc.py reads channel 0 and divides by 1e4 (cm -> 100 m units).
MATRIXCITY_DEPTH_INVALID = 65504.0


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


# --------------------------------------------------------------------------- pure conversions


def decode_carla_depth(rgb: np.ndarray) -> np.ndarray:
    """CARLA depth-camera PNG pixels uint8 [H, W, >=3] (R, G, B order) -> float32 [H, W] metres.

    Planar depth (camera z), as CARLA renders it. The far-plane code (all channels 255) is sky
    and becomes inf.
    """
    assert rgb.ndim == 3 and rgb.shape[2] >= 3 and rgb.dtype == np.uint8, (rgb.shape, rgb.dtype)
    px = rgb[..., :3].astype(np.int64)
    code = px[..., 0] + 256 * px[..., 1] + 65536 * px[..., 2]
    depth = (code.astype(np.float64) / _CARLA_DEPTH_MAX_CODE * CARLA_DEPTH_FAR_M).astype(np.float32)
    depth[code == _CARLA_DEPTH_MAX_CODE] = np.inf
    return depth


def matrixcity_depth_to_metres(depth_cm: np.ndarray) -> np.ndarray:
    """MatrixCity depth [H, W] in centimetres -> float32 metres; 65504 (float16 max), non-finite
    and non-positive values are invalid and become inf (sky)."""
    d = np.asarray(depth_cm, dtype=np.float64)
    bad = ~np.isfinite(d) | (d >= MATRIXCITY_DEPTH_INVALID) | (d <= 0)
    out = (d / 100.0).astype(np.float32)
    out[bad] = np.inf
    return out


def yaw_sequence_name(offset_deg: float) -> str:
    """`yaw045` for a yaw offset of 45 deg (wrapped to [0, 360), rounded to whole degrees)."""
    return f"yaw{int(round(offset_deg)) % 360:03d}"


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


# --------------------------------------------------------------------------- field checks


_fail, _numbers, _number, _int, _name = fields.fail, fields.numbers, fields.number, fields.integer, fields.name


def _rel_file(base: Path, where: str, value: Any, what: str, root: Path | None = None) -> Path:
    """A file named relative to `base` that stays inside `root` (default `base`) once '..' and
    symlinks are resolved, and is a regular file."""
    root = base if root is None else root
    if not isinstance(value, str) or not value or "\x00" in value:
        _fail(where, f"expected {what} (a path relative to {base}), got {value!r}")
    p = Path(os.path.normpath(base / value))
    if not fileio.inside(p, root):
        _fail(where, f"{what} {value!r} leaves {root} (through '..', an absolute path or a symlink)")
    if not p.is_file():
        _fail(where, f"{what} {p} not found" + (" (not a regular file)" if p.exists() else ""))
    return fileio.check_regular(p)


def _check_size(path: Path, where: str, width: int, height: int) -> int:
    w, h, c, _ = fileio.image_header(path)
    if (w, h) != (width, height):
        _fail(where, f"{path} is {w}x{h}, expected {width}x{height} (fields 'width', 'height')")
    return c


def _split_of(town: str, protocol, split: str | None, flag: str = "--split") -> str:
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


def _check_sequences(scene: PlannedScene, where: str) -> None:
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
               meta: dict, force: bool, progress: bool) -> Path:
    """Write planned scenes atomically; validates the result before moving it into place."""
    from tqdm import tqdm

    total = sum(len(s.ground) + len(s.aerial) for s in scenes)
    with DatasetWriter(out, name=name, protocol=protocol, overwrite=force, validate=True) as w, \
            tqdm(total=total, desc=f"import {name}", unit="frame", file=sys.stderr,
                 disable=None if progress else True) as bar:
        for s in scenes:
            ground = sorted(s.ground, key=lambda f: (f.sequence, f.index))
            groups = {"ground": _group_intrinsics(ground), "aerial": _group_intrinsics(s.aerial)}
            groups = {k: v or groups["ground"] for k, v in groups.items()}
            sw = w.scene(s.name, groups, meta=s.meta)
            for f in [*s.aerial, *ground]:
                px = fileio.read_image_uint8(f.image)
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


def _summary_line(out: Path, scenes: list[PlannedScene]) -> str:
    nseq = sum(len({f.sequence for f in s.ground}) for s in scenes)
    return (f"wrote {out}: {len(scenes)} scenes, {nseq} sequences, {sum(len(s.ground) for s in scenes)} ground "
            f"frames, {sum(len(s.aerial) for s in scenes)} aerial frames")


def _ordered_splits(scenes: list[PlannedScene], split_of: dict[str, str]) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {"train": [], "test": []}
    for s in scenes:
        out.setdefault(split_of[s.name], []).append(s.name)
    return out


# --------------------------------------------------------------------------- CARLA

CARLA_CAPTURE_FILE = "capture.json"
CARLA_FORMAT = "skyeyes-carla-capture"


def plan_carla(src: str | Path, protocol, split: str | None = None) -> tuple[list[PlannedScene], dict[str, str]]:
    """Read `<src>/capture.json` and check it (see docs/formats.md); returns scenes and their splits."""
    src = Path(src)
    jfile = src / CARLA_CAPTURE_FILE
    if not src.is_dir():
        raise UserError(f"{src}: not a folder (expected a CARLA capture folder with {CARLA_CAPTURE_FILE})")
    raw = fileio.read_json(jfile)
    if not isinstance(raw, dict) or raw.get("format") != CARLA_FORMAT:
        _fail(f"{jfile}: field 'format'", f"expected {CARLA_FORMAT!r}")
    if raw.get("version") != 1:
        _fail(f"{jfile}: field 'version'", f"expected 1, got {raw.get('version')!r}")
    frames = raw.get("frames")
    if not isinstance(frames, list) or not frames:
        _fail(f"{jfile}: field 'frames'", "expected a non-empty list of sensor records")
    scenes: dict[str, PlannedScene] = {}
    split_of: dict[str, str] = {}
    for i, rec in enumerate(frames):
        at = f"{jfile}: frames[{i}]"
        if not isinstance(rec, dict):
            _fail(at, "expected an object")
        known = {"kind", "town", "lane", "yaw_offset_deg", "sequence", "index", "image", "depth", "location",
                 "rotation", "fov", "width", "height"}
        for k in rec:
            if k not in known:
                _fail(f"{at}.{k}", f"unknown field (known: {', '.join(sorted(known))})")
        kind = rec.get("kind")
        if kind not in ("ground", "aerial"):
            _fail(f"{at}.kind", f"expected 'ground' or 'aerial', got {kind!r}")
        town = _name(f"{at}.town", rec.get("town"), "a town name such as 'Town04'")
        lane = _int(f"{at}.lane", rec.get("lane"), "the lane number")
        loc = _numbers(f"{at}.location", rec.get("location"), 3, "[x, y, z] in CARLA metres")
        rot = _numbers(f"{at}.rotation", rec.get("rotation"), 3, "[pitch, yaw, roll] in degrees")
        fov = _number(f"{at}.fov", rec.get("fov"), "the horizontal field of view in degrees, 0 < fov < 180", 0, 180)
        width = _int(f"{at}.width", rec.get("width"), "the image width in pixels", 1)
        height = _int(f"{at}.height", rec.get("height"), "the image height in pixels", 1)
        image = _rel_file(src, f"{at}.image", rec.get("image"), "RGB image")
        channels = _check_size(image, f"{at}.image", width, height)
        if channels not in (3, 4):
            _fail(f"{at}.image", f"{image} has {channels} channel(s), expected RGB")
        depth = None
        if rec.get("depth") is not None:
            dpath = _rel_file(src, f"{at}.depth", rec.get("depth"), "depth-camera PNG")
            if _check_size(dpath, f"{at}.depth", width, height) < 3:
                _fail(f"{at}.depth", f"{dpath} must be the depth camera's 3- or 4-channel encoded PNG")
            depth = (lambda p=dpath: decode_carla_depth(fileio.read_image_uint8(p)))
        seq = idx = None
        if kind == "ground":
            if rec.get("sequence") is not None:
                seq = _name(f"{at}.sequence", rec.get("sequence"), "a sequence name such as 'yaw045'")
            elif rec.get("yaw_offset_deg") is not None:
                seq = yaw_sequence_name(_number(f"{at}.yaw_offset_deg", rec.get("yaw_offset_deg"), "degrees"))
            else:
                _fail(at, "a ground frame needs 'yaw_offset_deg' (or 'sequence')")
            idx = _int(f"{at}.index", rec.get("index"), "the frame's position along the lane", 0, len(frames) - 1)
        cam = from_carla(loc, rot, fov, width, height)
        name = f"{town}-lane{lane:02d}"
        scene = scenes.setdefault(name, PlannedScene(name, meta={"source": "carla", "town": town, "lane": lane}))
        split_of[name] = _split_of(town, protocol, split)
        (scene.ground if kind == "ground" else scene.aerial).append(PlannedFrame(
            kind, image, cam.c2w, cam.intrinsics_dict(), depth, seq, idx))
    for s in scenes.values():
        if not s.ground:
            _fail(jfile, f"lane {s.name!r} has aerial frames but no ground frames")
        _check_sequences(s, str(jfile))
    ordered = [scenes[n] for n in sorted(scenes)]
    return ordered, split_of


def import_carla(src: str | Path, out: str | Path, *, protocol: str = "carla-town04", split: str | None = None,
                 name: str | None = None, force: bool = False, progress: bool = True) -> tuple[Path, list[PlannedScene]]:
    """Convert a CARLA capture folder into the canonical layout at `out`."""
    from ..protocol import load_protocol

    proto = load_protocol(protocol)
    scenes, split_of = plan_carla(src, proto, split)
    meta = {"source": "carla", "importer": "skyeyes-bench data import-carla", "src": str(src),
            "world": "CARLA world with y negated (right-handed, z up, metres)"}
    out = write_plan(Path(out), scenes, name=name or Path(out).name, protocol=proto.ref,
                     splits=_ordered_splits(scenes, split_of), meta=meta, force=force, progress=progress)
    return out, scenes


# --------------------------------------------------------------------------- MatrixCity

# NOTE: source layout from the MatrixCity repository (github.com/city-super/MatrixCity,
# scripts/load_aerial.py, load_street.py, generate_split.py, rgbd2pc.py):
#  - raw capture `<set>/<block>/transforms.json`: {"camera_angle_x": rad, "frames": [{"frame_index",
#    "rot_mat": 4x4}]}, image `<block>/<frame_index:04d>.png`; rot_mat's rotation is stored x0.01,
#    its translation in metres; camera axes OpenGL/NeRF.
#  - paper splits `pose/<block>/transforms_<set>.json`: {"camera_angle_x", "fl_x", "fl_y", "cx", "cy",
#    "w", "h", "frames": [{"file_path": relative to the JSON's folder, "transform_matrix": 4x4}]},
#    rotation orthonormal, translation in units of 100 m.
#  - depth: EXR, same relative path with .exr, channel 0 in centimetres (float16; 65504 invalid).


@dataclass
class _MCFrame:
    block: str
    kind: str  # "aerial" | "street"
    order: int
    image: Path
    c2w: np.ndarray  # [4, 4] OpenCV, metres
    intrinsics: dict
    depth: Path | None


def _mc_kind(path: Path, src: Path) -> str:
    kinds: set[str] = set()
    for parts in (path.relative_to(src).parts, src.resolve().parts):  # inside SRC first, then SRC's own name
        kinds = {k for k in ("aerial", "street") if any(k in p.lower() for p in parts)}
        if kinds:
            break
    if len(kinds) != 1:
        raise UserError(f"{path}: cannot tell whether these are aerial or street frames; keep MatrixCity's "
                        "folder names (a path component containing 'aerial' or 'street')")
    return kinds.pop()


def _mc_depth_path(image: Path, src: Path, depth_root: Path | None) -> Path | None:
    rel = image.relative_to(src) if image.is_relative_to(src) else Path(image.name)
    cands = [image.with_suffix(".exr"), image.parent.with_name(image.parent.name + "_depth") / (image.stem + ".exr")]
    if depth_root is not None:
        cands += [depth_root / rel.with_suffix(".exr"),
                  depth_root / rel.parent.with_name(rel.parent.name + "_depth") / (rel.stem + ".exr")]
    return next((c for c in cands if c.is_file()), None)


def _mc_intrinsics(raw: dict, jfile: Path, img_w: int, img_h: int) -> dict:
    """fx, fy, cx, cy for the image size actually on disk (scaled from the JSON's w, h if given)."""
    if all(k in raw for k in ("fl_x", "w", "h")):
        w = _number(f"{jfile}: field 'w'", raw["w"], "a width", 0)
        h = _number(f"{jfile}: field 'h'", raw["h"], "a height", 0)
        sw, sh = img_w / w, img_h / h
        fx = _number(f"{jfile}: field 'fl_x'", raw["fl_x"], "a focal length in pixels", 0) * sw
        fy = _number(f"{jfile}: field 'fl_y'", raw.get("fl_y", raw["fl_x"]), "a focal length in pixels", 0) * sh
        cx = _number(f"{jfile}: field 'cx'", raw.get("cx", w / 2), "a principal point x", 0) * sw
        cy = _number(f"{jfile}: field 'cy'", raw.get("cy", h / 2), "a principal point y", 0) * sh
        return {"width": img_w, "height": img_h, "fx": fx, "fy": fy, "cx": cx, "cy": cy}
    if "camera_angle_x" not in raw:
        _fail(jfile, "field 'camera_angle_x' missing (expected the horizontal field of view in radians)")
    ang = _number(f"{jfile}: field 'camera_angle_x'", raw["camera_angle_x"], "radians, 0 < angle < pi", 0, math.pi)
    K = intrinsics(math.degrees(ang), img_w, img_h)
    return {"width": img_w, "height": img_h, "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}


def _mc_read_pose_file(jfile: Path, src: Path, fmt: str, convention: str, depth_root: Path | None) -> list[_MCFrame]:
    raw = fileio.read_json(jfile)
    if not isinstance(raw, dict) or not isinstance(raw.get("frames"), list) or not raw["frames"]:
        _fail(jfile, "field 'frames' must be a non-empty list")
    kind = _mc_kind(jfile, src)
    block = str(jfile.parent.relative_to(src)) if fmt == "raw" else str(jfile.relative_to(src).with_suffix(""))
    out: list[_MCFrame] = []
    size = None
    intr = None
    for i, fr in enumerate(raw["frames"]):
        at = f"{jfile}: frames[{i}]"
        if not isinstance(fr, dict):
            _fail(at, "expected an object")
        if fmt == "raw":
            if "file_path" in fr:
                image = _rel_file(jfile.parent, f"{at}.file_path", fr["file_path"], "image", src)
            else:
                fi = _int(f"{at}.frame_index", fr.get("frame_index"), "the frame index")
                image = jfile.parent / f"{fi:04d}.png"
                if not image.is_file():
                    _fail(f"{at}.frame_index", f"image {image} not found")
            mat_key = "rot_mat"
        else:
            fp = fr.get("file_path")
            if isinstance(fp, str) and not Path(fp).suffix:
                fp += ".png"  # NeRF-style file paths may omit the extension
            image = _rel_file(jfile.parent, f"{at}.file_path", fp, "image", src)
            mat_key = "transform_matrix"
        mat = fr.get(mat_key)
        m = fields.matrix(f"{at}.{mat_key}", mat, 4, 4, "a pose matrix")
        m[3] = [0, 0, 0, 1]  # NOTE: MatrixCity's rgbd2pc.py also resets the last row (stored scaled)
        hdr = fileio.image_header(image)
        if size is None:
            size = hdr[:2]
            intr = _mc_intrinsics(raw, jfile, *size)
        elif hdr[:2] != size:
            _fail(f"{at}", f"{image} is {hdr[0]}x{hdr[1]}, other frames of this file are {size[0]}x{size[1]}")
        try:
            cam = from_matrixcity(m, pose_format=fmt, convention=convention, K=np.array(
                [[intr["fx"], 0, intr["cx"]], [0, intr["fy"], intr["cy"]], [0, 0, 1]]), width=size[0], height=size[1])
        except UserError as e:
            _fail(f"{at}.{mat_key}", f"{e} (is --pose-format {fmt} right for this file?)")
        out.append(_MCFrame(block, kind, i, image, cam.c2w, dict(intr), _mc_depth_path(image, src, depth_root)))
    return out


def _mc_depth_loader(path: Path | None):
    if path is None:
        return None
    return lambda: matrixcity_depth_to_metres(fileio.read_depth(path))


def plan_matrixcity(src: str | Path, protocol, *, town: str = "matrixcity", split: str | None = None,
                    pose_format: str = "auto", convention: str = "opengl", depth_root: str | Path | None = None,
                    aerial_radius_m: float = 60.0) -> tuple[list[PlannedScene], dict[str, str], dict]:
    """Find MatrixCity pose files under `src`, convert poses, cut street tracks into lanes and
    horizontal cube faces into sequences, resample to the protocol's step where a whole number
    of source steps matches it, and attach the aerial frames that look at each lane."""
    src = Path(src)
    if not src.is_dir():
        raise UserError(f"{src}: not a folder (expected a MatrixCity capture with transforms*.json files)")
    _name("--town", town, "a town name")
    raw_files = sorted(src.rglob("transforms.json"))
    paper_files = sorted(p for p in src.rglob("transforms_*.json"))
    if pose_format == "auto":
        pose_format = "raw" if raw_files else "paper"
    if pose_format not in ("raw", "paper"):
        raise UserError(f"--pose-format {pose_format!r}: expected auto, raw or paper")
    files = raw_files if pose_format == "raw" else paper_files
    if not files:
        want = "transforms.json" if pose_format == "raw" else "transforms_*.json"
        raise UserError(f"{src}: no {want} found (expected a MatrixCity capture, see docs/formats.md)")
    droot = Path(depth_root) if depth_root else None
    frames = [f for j in files for f in _mc_read_pose_file(j, src, pose_format, convention, droot)]
    street = [f for f in frames if f.kind == "street"]
    aerial = [f for f in frames if f.kind == "aerial"]
    if not street:
        raise UserError(f"{src}: no street frames found (pose files under a folder named 'street')")

    # 1. Horizontal cube faces only (the protocol's ground cameras have pitch 0).
    level = math.sin(math.radians(10.0))
    horizontal = [f for f in street if abs(f.c2w[2, 2]) < level]
    # 2. Capture points: frames of one block sharing a position (to 1 cm), ordered by first
    #    appearance, so point-major (all faces at a point) and face-major files both work.
    lanes: list[list[list[_MCFrame]]] = []  # lane -> point -> faces
    steps_all: list[float] = []
    for block in dict.fromkeys(f.block for f in horizontal):
        by_pos: dict[tuple, list[_MCFrame]] = {}
        for f in sorted((f for f in horizontal if f.block == block), key=lambda f: f.order):
            by_pos.setdefault(tuple(np.round(f.c2w[:3, 3] / 0.01).astype(np.int64)), []).append(f)
        pts = list(by_pos.values())
        pos = np.array([p[0].c2w[:3, 3] for p in pts])
        for idx in split_lanes(pos):
            lanes.append([pts[i] for i in idx])
            steps_all += list(np.linalg.norm(np.diff(pos[idx][:, :2], axis=0), axis=1))
    if not lanes:
        raise UserError(f"{src}: street frames form no lane of 2 or more capture points")
    src_step = float(np.median(steps_all))
    target = protocol.capture.ground_step_m
    k = resample_step(src_step, target)
    diffs = []
    if k is None:
        diffs.append(f"ground step {src_step:.2f} m kept (no whole number of source steps makes {target:g} m)")
        k = 1
    elif k > 1:
        diffs.append(f"ground step resampled from {src_step:.2f} m to {k * src_step:.2f} m (one capture point in {k})")
    scenes: list[PlannedScene] = []
    yaws_seen: set[str] = set()
    for li, lane in enumerate(lanes):
        lane = lane[::k]
        if len(lane) < 2:
            continue
        pos = np.array([p[0].c2w[:3, 3] for p in lane])
        travel = pos[-1, :2] - pos[0, :2]
        heading = math.degrees(math.atan2(travel[1], travel[0]))
        name = f"{town}-lane{len(scenes):02d}"
        scene = PlannedScene(name, meta={"source": "matrixcity", "town": town, "block": lane[0][0].block,
                                         "heading_deg": round(heading, 3)})
        # 3. One sequence per horizontal face direction, named by its yaw offset from the travel direction.
        seqs: dict[str, list[_MCFrame]] = {}
        for point in lane:
            for f in point:
                fwd = f.c2w[:3, 2]
                seq = yaw_sequence_name(math.degrees(math.atan2(fwd[1], fwd[0])) - heading)
                seqs.setdefault(seq, []).append(f)
        for seq, fs in sorted(seqs.items()):
            yaws_seen.add(seq)
            for i, f in enumerate(fs):
                scene.ground.append(PlannedFrame("ground", f.image, f.c2w, f.intrinsics, _mc_depth_loader(f.depth),
                                                 seq, i))
        # 4. Aerial frames whose optical axis meets the ground near a capture point of this lane.
        ground_z = float(pos[:, 2].mean()) - protocol.capture.ground_height_m
        for f in aerial:
            o, d = f.c2w[:3, 3], f.c2w[:3, 2]
            hit = o + (ground_z - o[2]) / d[2] * d if d[2] < -1e-6 else o
            if np.min(np.linalg.norm(pos[:, :2] - hit[:2], axis=1)) <= aerial_radius_m:
                scene.aerial.append(PlannedFrame("aerial", f.image, f.c2w, f.intrinsics, _mc_depth_loader(f.depth)))
        scene.meta["aerial_radius_m"] = aerial_radius_m
        scenes.append(scene)
    if not scenes:
        raise UserError(f"{src}: no lane keeps 2 or more capture points after resampling to {target:g} m")
    want = {yaw_sequence_name(y) for y in protocol.capture.yaws_deg}
    if yaws_seen != want:
        diffs.append(f"yaw offsets {sorted(yaws_seen)} (protocol: {sorted(want)}): public street captures are "
                     "cube-map faces; each horizontal face direction is one sequence")
    dropped = len(street) - len(horizontal)
    if dropped:
        diffs.append(f"{dropped} non-horizontal street frames (cube-map up/down faces) left out")
    if not aerial:
        diffs.append("no aerial frames found")
    sizes = sorted({(f.intrinsics["width"], f.intrinsics["height"]) for f in frames})
    if sizes != [(protocol.data.width, protocol.data.height)]:
        diffs.append(f"image sizes {', '.join(f'{w}x{h}' for w, h in sizes)} (protocol: "
                     f"{protocol.data.width}x{protocol.data.height}); frames are imported at their own size")
    fovs = sorted({round(math.degrees(2 * math.atan(f.intrinsics["width"] / (2 * f.intrinsics["fx"]))), 2)
                   for f in frames})
    if fovs != [round(protocol.data.fov_deg, 2)]:
        diffs.append(f"horizontal fov {', '.join(f'{v:g}' for v in fovs)} deg (protocol: {protocol.data.fov_deg:g})")
    split_name = _split_of(town, protocol, split)
    meta = {"source": "matrixcity", "pose_format": pose_format, "convention": convention,
            "source_step_m": round(src_step, 4), "step_m": round(k * src_step, 4),
            "protocol_differences": diffs}
    return scenes, {s.name: split_name for s in scenes}, meta


def import_matrixcity(src: str | Path, out: str | Path, *, protocol: str = "citysample-region5", town: str = "matrixcity",
                      split: str | None = None, pose_format: str = "auto", convention: str = "opengl",
                      depth_root: str | Path | None = None, aerial_radius_m: float = 60.0, name: str | None = None,
                      force: bool = False, progress: bool = True) -> tuple[Path, list[PlannedScene], dict]:
    """Convert a MatrixCity / CitySample capture into the canonical layout at `out`."""
    from ..protocol import load_protocol

    proto = load_protocol(protocol)
    scenes, split_of, meta = plan_matrixcity(src, proto, town=town, split=split, pose_format=pose_format,
                                             convention=convention, depth_root=depth_root,
                                             aerial_radius_m=aerial_radius_m)
    meta = {**meta, "importer": "skyeyes-bench data import-matrixcity", "src": str(src)}
    out = write_plan(Path(out), scenes, name=name or Path(out).name, protocol=proto.ref,
                     splits=_ordered_splits(scenes, split_of), meta=meta, force=force, progress=progress)
    return out, scenes, meta


# --------------------------------------------------------------------------- CLI handlers


def import_carla_cmd(args) -> int:
    out, scenes = import_carla(args.src, args.out, protocol=args.protocol, split=args.split, force=args.force,
                               progress=not args.no_progress)
    print(_summary_line(out, scenes))
    return 0


def import_matrixcity_cmd(args) -> int:
    out, scenes, meta = import_matrixcity(
        args.src, args.out, protocol=args.protocol, town=args.town, split=args.split, pose_format=args.pose_format,
        convention=args.convention, depth_root=args.depth_root, aerial_radius_m=args.aerial_radius,
        force=args.force, progress=not args.no_progress)
    print(_summary_line(out, scenes))
    for d in meta["protocol_differences"]:
        print(f"  differs from the protocol: {d}")
    return 0
