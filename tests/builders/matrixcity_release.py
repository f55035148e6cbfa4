"""A miniature MatrixCity download laid out as the public release ships it (github.com/city-super/
MatrixCity README "Data Structure", scripts/load_aerial.py, load_street.py, load_data.py), with the
truth an importer must recover. No tests here.

    MatrixCity/small_city/aerial/train/<block>/{transforms.json, transforms_origin.json, NNNN.png}
    MatrixCity/small_city/aerial/train/<block>.tar                  (the packed images; left beside)
    MatrixCity/small_city/aerial/pose/block_A/transforms_{train,test}.json   (paper splits, 100 m units)
    MatrixCity/small_city/street/{train,train_dense}/small_city_road_<dir>[_dense]/...   (5 m / 1 m)
    MatrixCity/small_city/street/pose/block_A/transforms_train.json
    MatrixCity/small_city_depth/<kind>/<set>/<block>_depth/NNNN.exr            float16 centimetres
    MatrixCity/small_city_depth_float32/aerial/<set>/<block>_depth/NNNN.exr    float32 centimetres

Raw poses: {"camera_angle_x", "frames": [{"frame_index", "rot_mat"}]}, rotation stored x0.01,
metres, OpenGL camera axes; `transforms.json` is `transforms_origin.json` without the views that
look straight down (the README's filtering of street views).
"""

import json
import math
import tarfile
from pathlib import Path

import numpy as np

from skyeyes_bench import imagefiles
from skyeyes_bench.cameras import Camera

W, H = 8, 6
GL = np.diag([1.0, -1.0, -1.0, 1.0])
FACES = [(0, 0), (90, 0), (180, 0), (270, 0), (0, 90), (0, -90)]  # 4 horizontal, up, down (cube map)
FOV = 90.0
#: A far aerial depth (cm) float16 cannot hold: 700 m, valid in the float32 tree.
FAR_CM = 70000.0


def _write_exr(path: Path, depth_cm: np.ndarray, fmt: str):
    import OpenImageIO as oiio

    path.parent.mkdir(parents=True, exist_ok=True)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(depth_cm.shape[1], depth_cm.shape[0], 3, fmt))
    px = np.minimum(depth_cm, 65504.0).astype(np.float16) if fmt == "half" else depth_cm.astype(np.float32)
    assert out.write_image(np.repeat(px[..., None], 3, axis=2))
    out.close()


def _street_points(start, direction, step, n, z=2.0):
    return [np.array([start[0] + direction[0] * step * i, start[1] + direction[1] * step * i, z]) for i in range(n)]


def make_release(root: Path, *, aerial_height=100.0, aerial_pitch=-45.0) -> dict:
    """Write the miniature download under `root` (= the `MatrixCity` folder); returns the truth:
    {"street": {image path: c2w}, "aerial": {image path: c2w}, "aerial_depth_m": {image path: [H, W]},
    "street_depth_m": {...}}. Road H runs along +x at y = 0, road V along +y at x = 300; aerial
    block_1 looks at road H, block_2 at road V, from `aerial_height` m above the ground (z = 0;
    street cameras at z = 2) at `aerial_pitch` deg."""
    city = root / "small_city"
    truth = {"street": {}, "aerial": {}, "aerial_depth_m": {}, "street_depth_m": {}}
    rng = np.random.default_rng(0)

    def block(kind, set_, name, cams, keep):
        """Raw block: transforms_origin.json lists all cams, transforms.json those with keep(cam)."""
        folder = city / kind / set_ / name
        folder.mkdir(parents=True)
        origin, kept = [], []
        for i, cam in enumerate(cams):
            img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
            imagefiles.write_image(folder / f"{i:04d}.png", img)
            m = cam.c2w @ GL
            m[:3, :3] *= 0.01  # NOTE: MatrixCity stores the raw rotation x 0.01
            rec = {"frame_index": i, "rot_mat": m.tolist()}
            origin.append(rec)
            d = rng.uniform(100, 20000, (H, W))
            d[0, 1] = 65504.0  # float16's sky code
            if kind == "aerial":
                d[1, 1] = FAR_CM
            _write_exr(root / "small_city_depth" / kind / set_ / f"{name}_depth" / f"{i:04d}.exr", d, "half")
            half = np.minimum(d, 65504.0).astype(np.float16).astype(np.float64)
            if kind == "aerial":
                _write_exr(root / "small_city_depth_float32" / kind / set_ / f"{name}_depth" / f"{i:04d}.exr", d,
                           "float")
                truth["aerial_depth_m"][str(folder / f"{i:04d}.png")] = (d / 100).astype(np.float32)
            else:
                truth["street_depth_m"][str(folder / f"{i:04d}.png")] = np.where(
                    half >= 65504, np.inf, half / 100).astype(np.float32)
            if keep(cam):
                kept.append(rec)
                truth[kind][str(folder / f"{i:04d}.png")] = cam.c2w
        for fname, frames in (("transforms_origin.json", origin), ("transforms.json", kept)):
            (folder / fname).write_text(json.dumps({"camera_angle_x": math.radians(FOV), "frames": frames}))
        with tarfile.open(folder.with_name(name + ".tar"), "w") as tar:  # as shipped; the importer reads the folder
            tar.add(folder / "0000.png", arcname=f"{name}/0000.png")
        return folder, kept

    def cube(points):
        return [Camera.from_ypr(p, y, pi, fov_deg=FOV, width=W, height=H) for p in points for y, pi in FACES]

    def not_down(cam):
        return cam.forward[2] > -0.9

    road_h, road_v = ((0.0, 0.0), (1.0, 0.0)), ((300.0, 0.0), (0.0, 1.0))
    streets = [
        block("street", "train_dense", "small_city_road_horizon_dense", cube(_street_points(*road_h, 1.0, 8)), not_down),
        block("street", "train_dense", "small_city_road_vertical_dense", cube(_street_points(*road_v, 1.0, 6)), not_down),
        block("street", "train", "small_city_road_horizon", cube(_street_points(*road_h, 5.0, 2)), not_down),
    ]
    # Aerial views beside each road, looking across it: the view centre lies on the road.
    back = aerial_height / math.tan(math.radians(-aerial_pitch))

    def aerial(points, yaw):
        return [Camera.from_ypr(p, yaw, aerial_pitch, fov_deg=FOV, width=W, height=H) for p in points]

    a1 = block("aerial", "train", "block_1", aerial([(x, -back, aerial_height) for x in (0.0, 3.0, 6.0)], 90), bool)
    a2 = block("aerial", "train", "block_2", aerial([(300.0 + back, y, aerial_height) for y in (0.0, 4.0)], 180), bool)

    # Paper splits (scripts/load_aerial.py, load_street.py): 100 m units, orthonormal rotation,
    # file_path relative to the JSON's folder, intrinsics of the full-size images.
    def paper(kind, split, blocks):
        frames = []
        for folder, kept in blocks:
            for rec in kept:
                m = np.array(rec["rot_mat"])
                m[:3, :3] *= 100
                m[:3, 3] /= 100
                frames.append({"file_path": f"../../{folder.parent.name}/{folder.name}/{rec['frame_index']:04d}.png",
                               "transform_matrix": m.tolist()})
        fl = 0.5 * W / math.tan(0.5 * math.radians(FOV))
        pose = {"camera_angle_x": math.radians(FOV), "fl_x": fl, "fl_y": fl, "k1": 0, "k2": 0, "k3": 0, "k4": 0,
                "p1": 0, "p2": 0, "cx": W / 2, "cy": H / 2, "w": float(W), "h": float(H), "frames": frames}
        out = city / kind / "pose" / "block_A" / f"transforms_{split}.json"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(pose))

    a1_test = block("aerial", "test", "block_1_test", aerial([(2.0, -back, aerial_height)], 90), bool)
    paper("aerial", "train", [a1, a2])
    paper("aerial", "test", [a1_test])
    paper("street", "train", streets[:2])
    return truth
