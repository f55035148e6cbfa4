"""CARLA capture folders -> canonical layout (format: docs/formats.md).

Poses go to the right-handed world (CARLA y negated, docs/formats.md); depth-camera PNGs are decoded
to float32 metres.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ... import fields, imagefiles, inputfiles
from ...cameras import from_carla
from ...errors import UserError
from .common import (PlannedFrame, PlannedScene, check_out, check_sequences, check_size, ordered_splits, rel_file,
                     town_split, write_plan, yaw_sequence_name)

_fail, _numbers, _number, _int, _name = fields.fail, fields.numbers, fields.number, fields.integer, fields.name

#: CARLA depth camera: 24-bit code over 3 channels, far plane at 1000 m.
#: NOTE: CARLA docs, "Sensors reference / Depth camera": normalized = (R + G*256 + B*256^2)
#: / (256^3 - 1); in metres = 1000 * normalized.
CARLA_DEPTH_FAR_M = 1000.0
_CARLA_DEPTH_MAX_CODE = 256**3 - 1


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


CARLA_CAPTURE_FILE = "capture.json"
CARLA_FORMAT = "skyeyes-carla-capture"


def plan_carla(src: str | Path, protocol, split: str | None = None) -> tuple[list[PlannedScene], dict[str, str]]:
    """Read `<src>/capture.json` and check it (see docs/formats.md); returns scenes and their splits."""
    src = Path(src)
    jfile = src / CARLA_CAPTURE_FILE
    if not src.is_dir():
        raise UserError(f"{src}: not a folder (expected a CARLA capture folder with {CARLA_CAPTURE_FILE})")
    raw = inputfiles.read_json(jfile)
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
        image = rel_file(src, f"{at}.image", rec.get("image"), "RGB image")
        channels = check_size(image, f"{at}.image", width, height)
        if channels not in (3, 4):
            _fail(f"{at}.image", f"{image} has {channels} channel(s), expected RGB")
        depth = None
        if rec.get("depth") is not None:
            dpath = rel_file(src, f"{at}.depth", rec.get("depth"), "depth-camera PNG")
            if check_size(dpath, f"{at}.depth", width, height) < 3:
                _fail(f"{at}.depth", f"{dpath} must be the depth camera's 3- or 4-channel encoded PNG")
            depth = (lambda p=dpath: decode_carla_depth(imagefiles.read_image_uint8(p)))
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
        split_of[name] = town_split(town, protocol, split)
        (scene.ground if kind == "ground" else scene.aerial).append(PlannedFrame(
            kind, image, cam.c2w, cam.intrinsics_dict(), depth, seq, idx))
    for s in scenes.values():
        if not s.ground:
            _fail(jfile, f"lane {s.name!r} has aerial frames but no ground frames")
        check_sequences(s, str(jfile))
    ordered = [scenes[n] for n in sorted(scenes)]
    return ordered, split_of


def import_carla(src: str | Path, out: str | Path, *, protocol: str = "carla-town04", split: str | None = None,
                 name: str | None = None, force: bool = False, progress: bool = True) -> tuple[Path, list[PlannedScene]]:
    """Convert a CARLA capture folder into the canonical layout at `out`."""
    from ...protocol import load_protocol

    check_out(out, force, [src])  # before any work: OUT never is, holds or lies inside SRC
    proto = load_protocol(protocol)
    scenes, split_of = plan_carla(src, proto, split)
    meta = {"source": "carla", "importer": "skyeyes-bench data import-carla", "src": str(src),
            "world": "CARLA world with y negated (right-handed, z up, metres)"}
    # The protocol whose data this is: carla-town04@2 and @3 (the default, the latest) score
    # carla-town04@1's frames, so the dataset says carla-town04@1 and every version scores it.
    out = write_plan(Path(out), scenes, name=name or Path(out).name, protocol=proto.data_ref,
                     splits=ordered_splits(scenes, split_of), meta=meta, force=force, progress=progress,
                     inputs=[src])
    return out, scenes
