"""MatrixCity / CitySample captures -> canonical layout (format: docs/formats.md).

Street tracks are cut into lanes, each horizontal cube-map face direction becomes a sequence,
resampled to the protocol's ground step where a whole number of source steps matches it; what
differs from the protocol is recorded in the dataset's meta.
"""

from __future__ import annotations

import fnmatch
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ... import fields, imagefiles, inputfiles
from ...cameras import from_matrixcity, intrinsics
from ...errors import UserError
from .common import (PlannedFrame, PlannedScene, check_out, ordered_splits, rel_file, resample_step, split_lanes,
                     town_split, write_plan, yaw_sequence_name)

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
# and from its README ("Data Structure"): `<set>/<block>/` also holds `transforms_origin.json`, the
# raw poses of every image before the filtering that made `transforms.json` (same raw layout); the
# images ship as `<block>.tar`; depth ships in sibling trees `<map>_depth/` (float16) and
# `<map>_depth_float32/` (aerial views), as `<kind>/<set>/<block>_depth/NNNN.exr`.

#: MatrixCity depth EXRs are centimetres; in float16 files the float16 maximum marks sky / invalid.
#: NOTE: MatrixCity scripts/load_data.py masks `== 65504` only when the file is float16; float32
#: depth (the `*_depth_float32` release) has no such code, so 655 m and beyond are valid there.
MATRIXCITY_DEPTH_INVALID = 65504.0

#: Raw-layout pose file beside `transforms.json` (every image before MatrixCity's own filtering);
#: it matches `transforms_*.json` but is not a paper split.
MATRIXCITY_ORIGIN_POSES = "transforms_origin.json"

#: Folder names of MatrixCity's maps; SRC must hold at most one of them.
MATRIXCITY_MAPS = ("small_city", "big_city", "aerial_street_fusion")

#: Aerial views further than this from the protocol's aerial pitch (deg), or by more than this
#: fraction from its altitude, are reported in `protocol_differences`.
AERIAL_PITCH_TOL_DEG = 1.0
AERIAL_ALTITUDE_TOL = 0.05


def matrixcity_depth_to_metres(depth_cm: np.ndarray, *, half: bool) -> np.ndarray:
    """MatrixCity depth [H, W] in centimetres -> float32 metres. Non-finite and non-positive
    values are invalid and become inf (sky); so is 65504 when the file stored float16 (`half`),
    where it is the code for sky / beyond range, never in float32 files."""
    d = np.asarray(depth_cm, dtype=np.float64)
    bad = ~np.isfinite(d) | (d <= 0)
    if half:
        bad |= d >= MATRIXCITY_DEPTH_INVALID
    out = (d / 100.0).astype(np.float32)
    out[bad] = np.inf
    return out


@dataclass
class _MCFrame:
    block: str  # the pose file's folder (raw) or path without suffix (paper), relative to SRC
    kind: str  # "aerial" | "street"
    order: int
    image: Path
    c2w: np.ndarray  # [4, 4] OpenCV, metres
    intrinsics: dict
    depth: Path | None
    names: frozenset = frozenset()  # folder names of its pose file and image under SRC (for --region)


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


def _depth_folders(folder: Path) -> list[Path]:
    """Where the depth of images in `folder` may be: the folder itself, `<folder>_depth/`, and
    `<folder>_depth/<folder>_depth/` (a release tar unpacked into a folder of its own name)."""
    d = folder.with_name(folder.name + "_depth")
    return [folder, d, d / d.name]


def _mc_depth_path(image: Path, src: Path, depth_roots: list[Path]) -> Path | None:
    rel = image.relative_to(src) if image.is_relative_to(src) else Path(image.name)
    if rel.parent.name and rel.parent.name == rel.parent.parent.name:  # <block>/<block>/NNNN.png
        rel = rel.parent.parent / rel.name
    cands = [f / (image.stem + ".exr") for f in _depth_folders(image.parent)]
    for root in depth_roots:
        cands += [f / (rel.stem + ".exr") for f in _depth_folders(root / rel.parent)]
    return next((c for c in cands if c.is_file()), None)


def default_depth_roots(src: Path) -> list[Path]:
    """The release's depth trees beside SRC: `<SRC>_depth_float32` first (aerial depth in float32,
    MatrixCity's recommendation), then `<SRC>_depth` (float16); those that exist."""
    src = Path(src).resolve()
    # NOTE: MatrixCity's README also spells one of these trees "..._depth_flaot32".
    names = [f"{src.name}_depth_float32", f"{src.name}_depth_flaot32", f"{src.name}_depth"]
    return [src.with_name(n) for n in names if src.with_name(n).is_dir()]


def _raw_image(folder: Path, index: int, where: str, src: Path) -> Path:
    """`<folder>/NNNN.png`, or `<folder>/<folder>/NNNN.png` (the block's tar unpacked into the
    block's own folder), inside `src` once symlinks are resolved; a one-line error that names the
    tar when it is still packed."""
    name = f"{index:04d}.png"
    for cand in (folder / name, folder / folder.name / name):
        if cand.is_file():
            if not inputfiles.inside(cand, src):
                _fail(where, f"image {cand} leaves {src} (through a symlink)")
            return inputfiles.check_regular(cand)
    tar = folder.with_name(folder.name + ".tar")
    hint = f" (unpack {tar} into {folder.parent} first)" if tar.is_file() else ""
    _fail(where, f"image {folder / name} not found{hint}")


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


def _mc_read_pose_file(jfile: Path, src: Path, fmt: str, convention: str, depth_roots: list[Path]) -> list[_MCFrame]:
    raw = inputfiles.read_json(jfile, root=src)  # a pose file linked from outside SRC is refused
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
                fi = _int(f"{at}.frame_index", fr.get("frame_index"), "the frame index", 0)
                image = _raw_image(jfile.parent, fi, f"{at}.frame_index", src)
            mat_key = "rot_mat"
        else:
            fp = fr.get("file_path")
            if isinstance(fp, str) and not Path(fp).suffix:
                fp += ".png"  # NeRF-style file paths may omit the extension
            if isinstance(fp, str) and "\x00" not in fp and not (jfile.parent / fp).exists():
                nested = Path(fp).parent / Path(fp).parent.name / Path(fp).name  # <block>/<block>/NNNN.png
                fp = str(nested) if (jfile.parent / nested).is_file() else fp
            image = rel_file(jfile.parent, f"{at}.file_path", fp, "image", src)
            mat_key = "transform_matrix"
        mat = fr.get(mat_key)
        m = fields.matrix(f"{at}.{mat_key}", mat, 4, 4, "a pose matrix")
        m[3] = [0, 0, 0, 1]  # NOTE: MatrixCity's rgbd2pc.py also resets the last row (stored scaled)
        hdr = imagefiles.image_header(image)
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
        names = frozenset(Path(block).parts) | frozenset(image.parent.relative_to(src).parts
                                                       if image.is_relative_to(src) else ())
        depth = _mc_depth_path(image, src, depth_roots)
        if depth is not None:  # beside the image (inside SRC) or in a depth folder, symlinks resolved
            if not any(inputfiles.inside(depth, r) for r in (src, *depth_roots)):
                _fail(f"{at}", f"depth {depth} leaves {src} and the depth folders (through a symlink)")
            inputfiles.check_regular(depth)
        out.append(_MCFrame(block, kind, i, image, cam.c2w, dict(intr), depth, names))
    return out


def _mc_depth_loader(path: Path | None):
    if path is None:
        return None
    return lambda: matrixcity_depth_to_metres(imagefiles.read_depth(path), half=imagefiles.image_header(path)[3] == "half")


def _pose_files(src: Path, pose_format: str, include: list[str] | None = None) -> tuple[Path, str, list[Path]]:
    """(SRC, possibly moved into the one MatrixCity map it holds, the pose format, its files).

    Raw: every `transforms.json` (never `transforms_origin.json`, the unfiltered raw poses).
    Paper: every `transforms_*.json` except `transforms_origin.json`. With `include` (glob
    patterns on the path relative to SRC), only the files that match one of them.
    """
    def keep(p: Path) -> bool:
        return not include or any(fnmatch.fnmatchcase(p.relative_to(src).as_posix(), g) for g in include)

    raw_files = sorted(src.rglob("transforms.json"))
    paper_files = sorted(p for p in src.rglob("transforms_*.json") if p.name != MATRIXCITY_ORIGIN_POSES)
    maps = sorted({part for j in [*raw_files, *paper_files] for part in j.relative_to(src).parts[:-1]
                   if part in MATRIXCITY_MAPS})
    if len(maps) > 1:
        raise UserError(f"{src}: holds several MatrixCity maps ({', '.join(maps)}); pass one as SRC, "
                        f"e.g. {src / maps[0]}")
    if maps and (src / maps[0]).is_dir() and src.name != maps[0]:  # the download's root: use its one map
        if not inputfiles.inside(src / maps[0], src):
            raise UserError(f"{src / maps[0]}: leaves {src} (a symlink); every file read must lie inside SRC")
        return _pose_files(src / maps[0], pose_format, include)
    raw_files, paper_files = [p for p in raw_files if keep(p)], [p for p in paper_files if keep(p)]
    if pose_format == "auto":
        pose_format = "raw" if raw_files else "paper"
    if pose_format not in ("raw", "paper"):
        raise UserError(f"--pose-format {pose_format!r}: expected auto, raw or paper")
    files = raw_files if pose_format == "raw" else paper_files
    if not files:
        want = "transforms.json" if pose_format == "raw" else "transforms_*.json"
        other = "" if pose_format == "raw" else f"; {MATRIXCITY_ORIGIN_POSES} holds raw poses"
        filt = f" matching --include {' '.join(include)}" if include else ""
        raise UserError(f"{src}: no {want}{filt} found (expected a MatrixCity capture, see docs/formats.md{other})")
    return src, pose_format, files


def _view_centre(f: _MCFrame, ground_z: float) -> np.ndarray:
    """Where the optical axis of a camera meets the plane z = ground_z (its position if it never does)."""
    o, d = f.c2w[:3, 3], f.c2w[:3, 2]
    return o + (ground_z - o[2]) / d[2] * d if d[2] < -1e-6 else o.copy()


def _region_of_lanes(centres: np.ndarray, aerial: list[_MCFrame], regions: dict[str, list[str]], ground_z: float,
                     radius: float) -> list[str | None]:
    """Per lane centre [L, 2]: the region (town) whose aerial blocks' view centres come nearest,
    None when none comes within `radius` m. A region is a list of aerial block names, each matched
    against the folder names of a frame's pose file and image (`block_10`, or a paper block `block_E`)."""
    near = np.full((len(centres), len(regions)), np.inf)
    known = sorted({n for f in aerial for n in f.names})
    for j, (town, blocks) in enumerate(regions.items()):
        for b in blocks:
            if b not in known:
                raise UserError(f"--region {town}={','.join(blocks)}: no aerial block {b!r} in SRC "
                                f"(aerial blocks: {', '.join(n for n in known if 'block' in n) or 'none'})")
        views = np.array([_view_centre(f, ground_z)[:2] for f in aerial if f.names & set(blocks)])
        near[:, j] = np.min(np.linalg.norm(centres[:, None, :] - views[None, :, :], axis=2), axis=1)
    names = list(regions)
    best = np.argmin(near, axis=1)
    return [names[b] if near[i, b] <= radius else None for i, b in enumerate(best)]


def plan_matrixcity(src: str | Path, protocol, *, town: str = "matrixcity", split: str | None = None,
                    pose_format: str = "auto", convention: str = "opengl",
                    depth_root: str | Path | list[str | Path] | None = None, aerial_radius_m: float = 60.0,
                    regions: dict[str, list[str]] | None = None,
                    include: list[str] | None = None) -> tuple[list[PlannedScene], dict[str, str], dict]:
    """Find MatrixCity pose files under `src`, convert poses, cut street tracks into lanes and
    horizontal cube faces into sequences, resample to the protocol's step where a whole number
    of source steps matches it, and attach the aerial frames that look at each lane.

    `regions` ({town: [aerial block, ...]}) names the scenes by region instead of `town`: each
    lane goes to the region whose aerial blocks look nearest to it (lanes no region covers within
    `aerial_radius_m` are left out), so one import holds a protocol's train and test regions.
    """
    src = Path(src)
    if not src.is_dir():
        raise UserError(f"{src}: not a folder (expected a MatrixCity capture with transforms*.json files)")
    if not (isinstance(aerial_radius_m, (int, float)) and math.isfinite(aerial_radius_m) and aerial_radius_m > 0):
        raise UserError(f"--aerial-radius {aerial_radius_m}: expected a finite distance in metres > 0")
    for t in ([*regions] if regions else [town]):
        _name("--region" if regions else "--town", t, "a town name")
    src, pose_format, files = _pose_files(src, pose_format, include)
    if depth_root is None:
        droots = default_depth_roots(src)
    else:
        droots = [Path(d) for d in ([depth_root] if isinstance(depth_root, (str, Path)) else depth_root)]
        for d in droots:
            if not d.is_dir():
                raise UserError(f"--depth-root {d}: not a folder")
    frames = [f for j in files for f in _mc_read_pose_file(j, src, pose_format, convention, droots)]
    street = [f for f in frames if f.kind == "street"]
    aerial = [f for f in frames if f.kind == "aerial"]
    if not street:
        raise UserError(f"{src}: no street frames found (pose files under a folder named 'street')")
    if regions and not aerial:
        raise UserError(f"{src}: --region needs aerial frames (pose files under a folder named 'aerial')")

    # 1. Horizontal cube faces only (the protocol's ground cameras have pitch 0).
    level = math.sin(math.radians(10.0))
    horizontal = [f for f in street if abs(f.c2w[2, 2]) < level]
    target = protocol.capture.ground_step_m
    lanes, block_steps, src_step, out_steps, diffs = _street_lanes(src, horizontal, target)
    # The ground under the street cameras, assumed at the protocol's camera height.
    ground_z = float(np.median([f.c2w[2, 3] for f in horizontal])) - protocol.capture.ground_height_m
    if regions:
        centres = np.array([np.mean([p[0].c2w[:2, 3] for p in lane], axis=0) for lane in lanes]).reshape(-1, 2)
        towns = _region_of_lanes(centres, aerial, regions, ground_z, aerial_radius_m)
        if towns.count(None):
            diffs.append(f"{towns.count(None)} of {len(lanes)} lanes outside every --region left out")
    else:
        towns = [town] * len(lanes)
    scenes, yaws_seen, attached = _lane_scenes(lanes, towns, aerial, protocol, aerial_radius_m)
    if not scenes:
        raise UserError(f"{src}: no lane keeps 2 or more capture points after resampling to {target:g} m"
                        + (" inside a --region" if regions else ""))
    want = {yaw_sequence_name(y) for y in protocol.capture.yaws_deg}
    if yaws_seen != want:
        diffs.append(f"yaw offsets {sorted(yaws_seen)} (protocol: {sorted(want)}): public street captures are "
                     "cube-map faces; each horizontal face direction is one sequence")
    dropped = len(street) - len(horizontal)
    if dropped:
        diffs.append(f"{dropped} non-horizontal street frames (cube-map up/down faces) left out")
    if not aerial:
        diffs.append("no aerial frames found")
    meta_aerial = _aerial_meta(attached, ground_z, protocol, diffs)
    _image_differences(frames, protocol, diffs)
    split_of = {s.name: town_split(s.meta["town"], protocol, split) for s in scenes}
    meta = {"source": "matrixcity", "pose_format": pose_format, "convention": convention,
            "source_step_m": round(src_step, 4), "step_m": out_steps[0] if len(out_steps) == 1 else out_steps,
            "block_steps_m": {b: round(st, 4) for b, (st, _) in block_steps.items()}, **meta_aerial,
            "depth_roots": [str(d) for d in droots], "protocol_differences": diffs}
    if regions:
        meta["regions"] = {t: list(b) for t, b in regions.items()}
    return scenes, split_of, meta


def _street_lanes(src: Path, horizontal: list[_MCFrame], target: float) -> tuple[
        list[list[list[_MCFrame]]], dict[str, tuple[float, int | None]], float, list[float], list[str]]:
    """Street lanes (lane -> capture point -> faces) of the horizontal frames, resampled towards the
    protocol's step `target`; each block's (source step, k), the median source step, the output
    steps, and the protocol differences they make."""
    # 2. Capture points: frames of one block sharing a position (to 1 cm), ordered by first
    #    appearance, so point-major (all faces at a point) and face-major files both work.
    # 3. Resampling per block: a download holds 5 m (`train`) and 1 m (`train_dense`) blocks.
    lanes: list[list[list[_MCFrame]]] = []  # lane -> point -> faces
    steps_all: list[float] = []
    block_steps: dict[str, tuple[float, int | None]] = {}  # block -> (source step, k)
    for block in dict.fromkeys(f.block for f in horizontal):
        by_pos: dict[tuple, list[_MCFrame]] = {}
        for f in sorted((f for f in horizontal if f.block == block), key=lambda f: f.order):
            by_pos.setdefault(tuple(np.round(f.c2w[:3, 3] / 0.01).astype(np.int64)), []).append(f)
        pts = list(by_pos.values())
        pos = np.array([p[0].c2w[:3, 3] for p in pts])
        cut = split_lanes(pos)
        if not cut:
            continue
        steps = np.concatenate([np.linalg.norm(np.diff(pos[idx][:, :2], axis=0), axis=1) for idx in cut])
        steps_all += list(steps)
        step = float(np.median(steps))
        k = resample_step(step, target)
        block_steps[block] = (step, k)
        lanes += [[pts[i] for i in idx][::k or 1] for idx in cut]
    lanes = [lane for lane in lanes if len(lane) >= 2]
    if not lanes:
        raise UserError(f"{src}: street frames form no lane of 2 or more capture points")
    src_step = float(np.median(steps_all))
    diffs = []
    for step, k in sorted(set((round(s, 2), k) for s, k in block_steps.values()), key=lambda t: t[0]):
        if k is None:
            diffs.append(f"ground step {step:.2f} m kept (no whole number of source steps makes {target:g} m)")
        elif k > 1:
            diffs.append(f"ground step resampled from {step:.2f} m to {k * step:.2f} m (one capture point in {k})")
    out_steps = sorted({round(s * (k or 1), 4) for s, k in block_steps.values()})
    return lanes, block_steps, src_step, out_steps, diffs


def _lane_scenes(lanes, towns: list[str | None], aerial: list[_MCFrame], protocol,
                 aerial_radius_m: float) -> tuple[list[PlannedScene], set[str], dict[int, _MCFrame]]:
    """A scene per lane that has a town: its ground sequences and the aerial frames that look at it;
    with the sequence names seen and the aerial frames attached to any scene (by id)."""
    scenes: list[PlannedScene] = []
    yaws_seen: set[str] = set()
    attached: dict[int, _MCFrame] = {}
    for lane, lane_town in zip(lanes, towns):
        if lane_town is None:
            continue
        pos = np.array([p[0].c2w[:3, 3] for p in lane])
        travel = pos[-1, :2] - pos[0, :2]
        heading = math.degrees(math.atan2(travel[1], travel[0]))
        name = f"{lane_town}-lane{sum(s.meta['town'] == lane_town for s in scenes):02d}"
        scene = PlannedScene(name, meta={"source": "matrixcity", "town": lane_town, "block": lane[0][0].block,
                                         "heading_deg": round(heading, 3)})
        # 4. One sequence per horizontal face direction, named by its yaw offset from the travel direction.
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
        # 5. Aerial frames whose optical axis meets the ground near a capture point of this lane.
        lane_ground_z = float(pos[:, 2].mean()) - protocol.capture.ground_height_m
        for f in aerial:
            hit = _view_centre(f, lane_ground_z)
            if np.min(np.linalg.norm(pos[:, :2] - hit[:2], axis=1)) <= aerial_radius_m:
                scene.aerial.append(PlannedFrame("aerial", f.image, f.c2w, f.intrinsics, _mc_depth_loader(f.depth)))
                attached[id(f)] = f
        scene.meta["aerial_radius_m"] = aerial_radius_m
        scenes.append(scene)
    return scenes, yaws_seen, attached


def _aerial_meta(attached: dict[int, _MCFrame], ground_z: float, protocol, diffs: list[str]) -> dict:
    """The aerial views the dataset holds against the protocol's aerial pitch and altitude: their
    ranges for the dataset's meta; differences appended to `diffs`."""
    meta_aerial = {}
    if attached:
        used = list(attached.values())
        pitches = [math.degrees(math.asin(float(np.clip(f.c2w[2, 2], -1, 1)))) for f in used]
        alts = [float(f.c2w[2, 3]) - ground_z for f in used]
        want_p, want_a = protocol.capture.aerial_pitch_deg, protocol.capture.aerial_height_m
        meta_aerial = {"aerial_pitch_deg": [round(min(pitches), 2), round(max(pitches), 2)],
                       "aerial_altitude_m": [round(min(alts), 2), round(max(alts), 2)]}
        if max(abs(p - want_p) for p in pitches) > AERIAL_PITCH_TOL_DEG:
            diffs.append(f"aerial pitch {min(pitches):.1f}..{max(pitches):.1f} deg (protocol: {want_p:g})")
        if max(abs(a - want_a) for a in alts) > AERIAL_ALTITUDE_TOL * want_a:
            diffs.append(f"aerial altitude {min(alts):.1f}..{max(alts):.1f} m above the ground under the street "
                         f"cameras (protocol: {want_a:g})")
    return meta_aerial


def _image_differences(frames: list[_MCFrame], protocol, diffs: list[str]) -> None:
    """Image sizes and fields of view that differ from the protocol's, appended to `diffs`."""
    sizes = sorted({(f.intrinsics["width"], f.intrinsics["height"]) for f in frames})
    if sizes != [(protocol.data.width, protocol.data.height)]:
        diffs.append(f"image sizes {', '.join(f'{w}x{h}' for w, h in sizes)} (protocol: "
                     f"{protocol.data.width}x{protocol.data.height}); frames are imported at their own size")
    fovs = sorted({round(math.degrees(2 * math.atan(f.intrinsics["width"] / (2 * f.intrinsics["fx"]))), 2)
                   for f in frames})
    if fovs != [round(protocol.data.fov_deg, 2)]:
        diffs.append(f"horizontal fov {', '.join(f'{v:g}' for v in fovs)} deg (protocol: {protocol.data.fov_deg:g})")


def import_matrixcity(src: str | Path, out: str | Path, *, protocol: str = "citysample-region5", town: str = "matrixcity",
                      split: str | None = None, pose_format: str = "auto", convention: str = "opengl",
                      depth_root: str | Path | list[str | Path] | None = None, aerial_radius_m: float = 60.0,
                      regions: dict[str, list[str]] | None = None, include: list[str] | None = None,
                      name: str | None = None,
                      force: bool = False, progress: bool = True) -> tuple[Path, list[PlannedScene], dict]:
    """Convert a MatrixCity / CitySample capture into the canonical layout at `out`."""
    from ...protocol import load_protocol

    given = [depth_root] if isinstance(depth_root, (str, Path)) else list(depth_root or [])
    check_out(out, force, [src, *given], _INPUTS_ARE)  # before any work: OUT is never SRC, around it or in it
    proto = load_protocol(protocol)
    scenes, split_of, meta = plan_matrixcity(src, proto, town=town, split=split, pose_format=pose_format,
                                             convention=convention, depth_root=depth_root,
                                             aerial_radius_m=aerial_radius_m, regions=regions, include=include)
    meta = {**meta, "importer": "skyeyes-bench data import-matrixcity", "src": str(src)}
    # The protocol whose data this is (citysample-region5@2 and @3 score citysample-region5@1's frames).
    out = write_plan(Path(out), scenes, name=name or Path(out).name, protocol=proto.data_ref,
                     splits=ordered_splits(scenes, split_of), meta=meta, force=force, progress=progress,
                     inputs=[src, *meta["depth_roots"]], inputs_are=_INPUTS_ARE)
    return out, scenes, meta


_INPUTS_ARE = "the capture (SRC and its depth folders)"
