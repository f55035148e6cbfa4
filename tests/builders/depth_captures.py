"""Small CARLA and MatrixCity captures of one known scene, rendered exactly with depth for ground
and aerial views alike, so the depth-based metrics have consistent geometry to work on after an
importer has read them (shared by the carla-town04@2 / citysample-region5@2 tests; no tests here).

The scene, in our world (right-handed, z up, metres): textured ground z = 0, a block 6 m high at
y in [-60, -3] beside the lane, sky above. The lane runs along +x at y = 0 with ground cameras
2 m up every 2 m, looking along it (yaw offset 0) and back (180); the aerial views look at it
across the block at pitch -45 deg, so the block hides the ground at about y in [-3, 3] from
them, and its side facing the lane too. A ground view thus holds seen ground (beyond the
shadow, and the block's top edge, within the depth test's one-pixel leniency) and unseen
ground, block side and sky (the aerial views see no sky): 11% (CARLA) and 25% (MatrixCity)
of the pixels are seen. The aerial views are 160x128 so that their pixels (~1-2 m on the
ground) are finer than the block; at 40x32 (~7 m) the block fell between their pixel centres
and the depth test's 1% tolerance (0.7-1.4 m there) let them "see" the back of it.

The writers put the files where the importers look for them, in the formats they decode: CARLA's
24-bit depth code (`captures._encode_carla_depth`), MatrixCity's centimetre EXRs laid out as the
release ships them (float16 street depth in `<map>_depth/`, float32 aerial depth in
`<map>_depth_float32/`).
"""

import json
import math
from pathlib import Path

import numpy as np
from builders.captures import GL, _encode_carla_depth
from builders.matrixcity_release import _write_exr

from skyeyes_bench import imagefiles
from skyeyes_bench.cameras import Camera, from_carla

W, H = 40, 32  # ground frames: about the smallest SSIM (11x11 window) and LPIPS-AlexNet (two max-pools) take
AW, AH = 160, 128  # aerial views: pixels of ~1-2 m on the ground, finer than the block
FOV = 90.0
SKY = np.array([0.55, 0.70, 0.90])
BLOCK_LO, BLOCK_HI = np.array([-100.0, -60.0, 0.0]), np.array([100.0, -3.0, 6.0])


def _texture(a: np.ndarray, b: np.ndarray, phase: float) -> np.ndarray:
    """A smooth colour texture of two surface coordinates [N] -> [N, 3] in [0.1, 0.9]."""
    k = np.arange(3)[None, :]
    return 0.5 + 0.25 * np.sin(0.9 * a[:, None] + phase + k) * np.cos(0.6 * b[:, None] + 0.5 * k) \
        + 0.15 * np.sin(2.3 * a[:, None] - 1.7 * b[:, None] + k)


def render(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """The scene seen by `cam`: RGB uint8 [H, W, 3] and planar depth float32 [H, W] (+inf: sky)."""
    o, d = cam.rays(normalize=False)  # [N, 3]; camera z = 1, so the ray parameter is planar depth
    n = len(d)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(d[:, 2] < 0, -o[:, 2] / d[:, 2], np.inf)
        t1, t2 = (BLOCK_LO - o) / d, (BLOCK_HI - o) / d  # slabs of the block
        t_near = np.nanmax(np.minimum(t1, t2), axis=1)
        t_far = np.nanmin(np.maximum(t1, t2), axis=1)
    t_block = np.where((t_near <= t_far) & (t_near > 0), t_near, np.inf)
    t = np.minimum(t_ground, t_block)
    p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    rgb = np.broadcast_to(SKY, (n, 3)).copy()
    ground, block = np.isfinite(t) & (t_ground <= t_block), np.isfinite(t) & (t_block < t_ground)
    rgb[ground] = _texture(p[ground, 0], p[ground, 1], 0.0)
    rgb[block] = _texture(p[block, 0], p[block, 2], 2.0)
    px = np.rint(np.clip(rgb, 0, 1) * 255).astype(np.uint8).reshape(cam.height, cam.width, 3)
    return px, t.astype(np.float32).reshape(cam.height, cam.width)


# --------------------------------------------------------------------------- CARLA


def make_carla_depth(src: Path, *, frames: int = 4) -> dict:
    """`<src>/capture.json` (docs/formats.md): Town04 lane 0 (test) with yaw offsets 0 (along the
    lane) and 180 (back along it), `frames` ground frames each, and two aerial
    views 52 m up; Town01 lane 0 (train) with 2 ground frames. Every record has a depth PNG.
    Returns {image path relative to src: {"rgb", "depth", "camera"}} (our world)."""
    (src / "rgb").mkdir(parents=True)
    (src / "depth").mkdir()
    recs, truth = [], {}

    def add(kind, town, lane, loc, rot, **extra):
        n = len(recs)
        w, h = (W, H) if kind == "ground" else (AW, AH)
        cam = from_carla(loc, rot, FOV, w, h)
        rgb, depth = render(cam)
        code_rgb, _ = _encode_carla_depth(np.minimum(depth, 1000.0).astype(np.float64))
        image, dfile = f"rgb/{n:06d}.png", f"depth/{n:06d}.png"
        imagefiles.write_image(src / image, rgb)
        imagefiles.write_image(src / dfile, code_rgb)
        recs.append({"kind": kind, "town": town, "lane": lane, "image": image, "depth": dfile, "location": loc,
                     "rotation": rot, "fov": FOV, "width": w, "height": h, **extra})
        truth[image] = {"rgb": rgb, "depth": depth, "camera": cam}

    for off in (0.0, 180.0):
        for i in range(frames):
            add("ground", "Town04", 0, [2.0 * i, 0.0, 2.0], [0.0, off, 0.0], yaw_offset_deg=off, index=i)
    for x in (0.0, 2.0 * (frames - 1)):  # CARLA y = -(our y); yaw -90 looks along CARLA -y = our +y
        add("aerial", "Town04", 0, [x, 52.0, 52.0], [-45.0, -90.0, 0.0])
    for i in range(2):
        add("ground", "Town01", 0, [2.0 * i, 0.0, 2.0], [0.0, 0.0, 0.0], yaw_offset_deg=0.0, index=i)
    (src / "capture.json").write_text(json.dumps({"format": "skyeyes-carla-capture", "version": 1, "frames": recs}))
    return truth


# --------------------------------------------------------------------------- MatrixCity


def make_matrixcity_depth(root: Path, *, frames: int = 4) -> tuple[Path, dict]:
    """A MatrixCity raw capture under `root` as the release lays it out: SRC = `root/small_city`
    with street block `street/train/road_a` (faces yaw 0 and 180 at `frames` points every 2 m)
    and aerial block `aerial/train/block_1` (two views 100 m up); street depth in
    `root/small_city_depth` (float16 cm, 65504 for sky), aerial depth in
    `root/small_city_depth_float32` (float32 cm). Returns SRC and {image path: {"rgb", "depth",
    "camera"}}."""
    src = root / "small_city"
    truth = {}

    def block(kind: str, name: str, cams: list[Camera]) -> None:
        folder = src / kind / "train" / name
        folder.mkdir(parents=True)
        recs = []
        for i, cam in enumerate(cams):
            rgb, depth = render(cam)
            imagefiles.write_image(folder / f"{i:04d}.png", rgb)
            m = cam.c2w @ GL
            m[:3, :3] *= 0.01  # NOTE: MatrixCity stores the raw rotation x 0.01
            recs.append({"frame_index": i, "rot_mat": m.tolist()})
            tree, fmt = ("small_city_depth_float32", "float") if kind == "aerial" else ("small_city_depth", "half")
            cm = np.where(np.isfinite(depth), depth.astype(np.float64) * 100.0, 65504.0)
            _write_exr(root / tree / kind / "train" / f"{name}_depth" / f"{i:04d}.exr", cm, fmt)
            truth[str(folder / f"{i:04d}.png")] = {"rgb": rgb, "depth": depth, "camera": cam}
        (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": math.radians(FOV), "frames": recs}))

    block("street", "road_a", [Camera.from_ypr((2.0 * i, 0.0, 2.0), yaw, 0.0, fov_deg=FOV, width=W, height=H)
                               for i in range(frames) for yaw in (0.0, 180.0)])
    block("aerial", "block_1", [Camera.from_ypr((x, -100.0, 100.0), 90.0, -45.0, fov_deg=FOV, width=AW, height=AH)
                                for x in (0.0, 2.0 * (frames - 1))])
    return src, truth
