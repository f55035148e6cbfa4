"""Small CARLA and MatrixCity captures written by hand, with the truth each importer must recover
(shared by the importer, fuzz and hostile-input tests; no tests here)."""

import json
import math
from pathlib import Path

import numpy as np

from skyeyes_bench import imagefiles
from skyeyes_bench.cameras import Camera

W, H = 8, 6


def _rgba(seed):
    """RGBA with opaque alpha, as CARLA's camera writes (OpenImageIO would premultiply other alpha)."""
    px = np.random.default_rng(seed).integers(0, 256, (H, W, 4), dtype=np.uint8)
    px[..., 3] = 255
    return px


# --------------------------------------------------------------------------- CARLA fixture


def _encode_carla_depth(metres):
    """Inverse of CARLA's depth code, written here: code = round(d / 1000 * (2^24 - 1))."""
    code = np.where(np.isinf(metres), 2**24 - 1, np.rint(metres / 1000.0 * (2**24 - 1))).astype(np.int64)
    rgb = np.stack([code & 255, (code >> 8) & 255, code >> 16], axis=-1).astype(np.uint8)
    return rgb, code


def make_carla(src: Path) -> dict:
    """Town04 lane 3: yaws 0 and 45, 3 frames each, 2 aerial; Town01 lane 0: yaw 0, 2 frames."""
    (src / "rgb").mkdir(parents=True)
    (src / "depth").mkdir()
    frames, truth = [], {}
    n = 0

    def add(kind, town, lane, loc, rot, **extra):
        nonlocal n
        img = _rgba(n)
        imagefiles._write_pixels(src / "rgb" / f"{n:06d}.png", img, "uint8")  # 4 channels, like CARLA's BGRA->PNG
        rec = {"kind": kind, "town": town, "lane": lane, "image": f"rgb/{n:06d}.png", "location": loc,
               "rotation": rot, "fov": 90.0, "width": W, "height": H, **extra}
        if kind == "ground":
            d = np.random.default_rng(n).uniform(0.5, 300, (H, W))
            d[0, 0] = np.inf
            rgb, code = _encode_carla_depth(d)
            imagefiles.write_image(src / "depth" / f"{n:06d}.png", rgb)
            rec["depth"] = f"depth/{n:06d}.png"
            truth[rec["image"]] = {"code": code, "rgb": img[..., :3], "loc": loc, "rot": rot}
        else:
            truth[rec["image"]] = {"rgb": img[..., :3], "loc": loc, "rot": rot}
        frames.append(rec)
        n += 1

    for k, off in enumerate((0, 45)):
        for i in reversed(range(3)):  # out of order on purpose
            add("ground", "Town04", 3, [10.0 + 2 * i, 5.0, 2.0], [0.0, 30.0 + off, 0.0], yaw_offset_deg=off, index=i)
    for a in range(2):
        add("aerial", "Town04", 3, [10.0 + 2 * a, 5.0, 52.0], [-45.0, 30.0, 0.0])
    for i in range(2):
        add("ground", "Town01", 0, [0.0, -2.0 * i, 2.0], [0.0, -90.0, 3.0], sequence="yaw000", index=i)
    (src / "capture.json").write_text(json.dumps({"format": "skyeyes-carla-capture", "version": 1, "frames": frames}))
    return truth


# --------------------------------------------------------------------------- MatrixCity fixture

GL = np.diag([1.0, -1.0, -1.0, 1.0])
FACES = [(0, 0), (90, 0), (180, 0), (270, 0), (0, 90), (0, -90)]  # (yaw, pitch): 4 horizontal + up + down


def _write_half_exr(path: Path, depth_cm: np.ndarray):
    import OpenImageIO as oiio

    path.parent.mkdir(parents=True, exist_ok=True)
    out = oiio.ImageOutput.create(str(path))
    spec = oiio.ImageSpec(depth_cm.shape[1], depth_cm.shape[0], 3, "half")
    assert out.open(str(path), spec)
    assert out.write_image(np.repeat(depth_cm.astype(np.float16)[..., None], 3, axis=2))
    out.close()


def _street_tracks(step):
    """Two streets: along +x from (0, 0) and, after a jump, along +y from (100, 50)."""
    a = [np.array([step * i, 0.0, 2.0]) for i in range(int(6 / step) + 1)]
    b = [np.array([100.0, 50.0 + step * i, 2.0]) for i in range(int(4 / step) + 1)]
    return a + b


def make_matrixcity(src: Path, *, step=1.0, paper=False, depth=True, face_major=False) -> dict:
    """A MatrixCity-like capture: cube faces at every street point, three aerial views."""
    truth = {}
    fov = 90.0
    angle_x = math.radians(fov)

    def block(folder: Path, cams, with_depth):
        folder.mkdir(parents=True, exist_ok=True)
        frames = []
        for i, cam in enumerate(cams):
            img = _rgba(1000 + len(truth))[..., :3]
            imagefiles.write_image(folder / f"{i:04d}.png", img)
            gl = cam.c2w @ GL
            if paper:
                m = gl.copy()
                m[:3, 3] /= 100.0
                frames.append({"file_path": f"../../{folder.parent.name}/{folder.name}/{i:04d}.png",
                               "transform_matrix": m.tolist()})
            else:
                m = gl.copy()
                m[:3, :3] *= 0.01
                frames.append({"frame_index": i, "rot_mat": m.tolist()})
            t = {"c2w": cam.c2w, "rgb": img}
            if with_depth:
                d = np.random.default_rng(i).uniform(50, 30000, (H, W))  # centimetres
                d[1, 2] = 65504.0
                _write_half_exr(folder.parent / f"{folder.name}_depth" / f"{i:04d}.exr", d)
                t["depth_m"] = np.where(d.astype(np.float16) >= 65504, np.inf,
                                        d.astype(np.float16).astype(np.float64) / 100).astype(np.float32)
            truth[(folder.name, i)] = t
        return frames

    street_cams = [Camera.from_ypr(p, y, pi, fov_deg=fov, width=W, height=H)
                   for p in _street_tracks(step) for y, pi in FACES]
    if face_major:  # all points of face 0, then of face 1, ...
        street_cams = [street_cams[i * len(FACES) + k] for k in range(len(FACES))
                       for i in range(len(street_cams) // len(FACES))]
    aerial_cams = [Camera.from_ypr((x, -100.0, 102.0), 90, -45, fov_deg=fov, width=W, height=H)
                   for x in (0.0, 6.0)]  # 100 m up, pitch -45: looks at (x, 2, 0), beside lane 0
    aerial_cams.append(Camera.from_ypr((1000.0, 1000.0, 102.0), 0, -45, fov_deg=fov, width=W, height=H))  # far away
    s_frames = block(src / "street" / "train" / "road_a", street_cams, depth)
    a_frames = block(src / "aerial" / "train" / "block_1", aerial_cams, False)
    if paper:
        for kind, frames in (("street", s_frames), ("aerial", a_frames)):
            pose = {"camera_angle_x": angle_x, "fl_x": W / 2, "fl_y": W / 2, "cx": W / 2, "cy": H / 2,
                    "w": float(W), "h": float(H), "frames": frames}
            (src / kind / "pose" / "block_A").mkdir(parents=True)
            (src / kind / "pose" / "block_A" / "transforms_train.json").write_text(json.dumps(pose))
    else:
        for folder, frames in ((src / "street" / "train" / "road_a", s_frames),
                               (src / "aerial" / "train" / "block_1", a_frames)):
            (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": angle_x, "frames": frames}))
    return truth
