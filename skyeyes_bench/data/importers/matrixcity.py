"""MatrixCity / CitySample captures -> canonical layout (format: docs/formats.md).

Street tracks are cut into lanes, each horizontal cube-map face direction becomes a sequence,
resampled to the protocol's ground step where a whole number of source steps matches it; what
differs from the protocol is recorded in the dataset's meta.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ... import fields, fileio
from ...cameras import from_matrixcity, intrinsics
from ...errors import UserError
from .common import PlannedFrame, PlannedScene, ordered_splits, rel_file, town_split, write_plan, yaw_sequence_name

_fail, _number, _int, _name = fields.fail, fields.number, fields.integer, fields.name

# NOTE: source layout from the MatrixCity repository (github.com/city-super/MatrixCity,
# scripts/load_aerial.py, load_street.py, generate_split.py, rgbd2pc.py):
#  - raw capture `<set>/<block>/transforms.json`: {"camera_angle_x": rad, "frames": [{"frame_index",
#    "rot_mat": 4x4}]}, image `<block>/<frame_index:04d>.png`; rot_mat's rotation is stored x0.01,
#    its translation in metres; camera axes OpenGL/NeRF.
#  - paper splits `pose/<block>/transforms_<set>.json`: {"camera_angle_x", "fl_x", "fl_y", "cx", "cy",
#    "w", "h", "frames": [{"file_path": relative to the JSON's folder, "transform_matrix": 4x4}]},
#    rotation orthonormal, translation in units of 100 m.
#  - depth: EXR, same relative path with .exr, channel 0 in centimetres (float16; 65504 invalid).

#: MatrixCity depth EXRs are float16 centimetres; the float16 maximum marks sky / invalid.
#: NOTE: MatrixCity scripts/rgbd2pc.py reads channel 0 and divides by 1e4 (cm -> 100 m units).
MATRIXCITY_DEPTH_INVALID = 65504.0


def matrixcity_depth_to_metres(depth_cm: np.ndarray) -> np.ndarray:
    """MatrixCity depth [H, W] in centimetres -> float32 metres; 65504 (float16 max), non-finite
    and non-positive values are invalid and become inf (sky)."""
    d = np.asarray(depth_cm, dtype=np.float64)
    bad = ~np.isfinite(d) | (d >= MATRIXCITY_DEPTH_INVALID) | (d <= 0)
    out = (d / 100.0).astype(np.float32)
    out[bad] = np.inf
    return out


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
                image = rel_file(jfile.parent, f"{at}.file_path", fr["file_path"], "image", src)
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
            image = rel_file(jfile.parent, f"{at}.file_path", fp, "image", src)
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
    split_name = town_split(town, protocol, split)
    meta = {"source": "matrixcity", "pose_format": pose_format, "convention": convention,
            "source_step_m": round(src_step, 4), "step_m": round(k * src_step, 4),
            "protocol_differences": diffs}
    return scenes, {s.name: split_name for s in scenes}, meta


def import_matrixcity(src: str | Path, out: str | Path, *, protocol: str = "citysample-region5", town: str = "matrixcity",
                      split: str | None = None, pose_format: str = "auto", convention: str = "opengl",
                      depth_root: str | Path | None = None, aerial_radius_m: float = 60.0, name: str | None = None,
                      force: bool = False, progress: bool = True) -> tuple[Path, list[PlannedScene], dict]:
    """Convert a MatrixCity / CitySample capture into the canonical layout at `out`."""
    from ...protocol import load_protocol

    proto = load_protocol(protocol)
    scenes, split_of, meta = plan_matrixcity(src, proto, town=town, split=split, pose_format=pose_format,
                                             convention=convention, depth_root=depth_root,
                                             aerial_radius_m=aerial_radius_m)
    meta = {**meta, "importer": "skyeyes-bench data import-matrixcity", "src": str(src)}
    out = write_plan(Path(out), scenes, name=name or Path(out).name, protocol=proto.ref,
                     splits=ordered_splits(scenes, split_of), meta=meta, force=force, progress=progress)
    return out, scenes, meta
