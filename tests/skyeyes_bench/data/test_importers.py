"""CARLA and MatrixCity importers on small hand-written captures (builders.captures); checked against independent
arithmetic (poses, depth codes), grouping into lanes / sequences, and atomic, one-line failure."""

import json
import os
from pathlib import Path

import numpy as np
import pytest
from builders.captures import H, W, make_carla, make_matrixcity
from conftest import run_cli

from skyeyes_bench import imagefiles
from skyeyes_bench.data.importers import resample_step, split_lanes
from skyeyes_bench.data.layout import open_dataset


@pytest.fixture
def carla_src(tmp_path):
    src = tmp_path / "carla"
    return src, make_carla(src)


def _carla_forward_right(pitch, yaw, roll):
    """Forward and right of a CARLA camera in our world (CARLA y negated), by hand."""
    p, y, r = np.deg2rad([pitch, yaw, roll])
    fwd = np.array([np.cos(p) * np.cos(y), np.cos(p) * np.sin(y), np.sin(p)])
    right0 = np.array([-np.sin(y), np.cos(y), 0.0])
    up0 = np.array([-np.cos(y) * np.sin(p), -np.sin(y) * np.sin(p), np.cos(p)])
    flip = np.array([1.0, -1.0, 1.0])
    return fwd * flip, (np.cos(r) * right0 - np.sin(r) * up0) * flip


def test_import_carla(carla_src, tmp_path):
    src, truth = carla_src
    out = tmp_path / "out"
    _, stdout, err = run_cli("data", "import-carla", str(src), str(out), tty=True)
    assert stdout.strip() == f"wrote {out}: 2 scenes, 3 sequences, 8 ground frames, 2 aerial frames"
    assert "import out" in err  # the progress bar (drawn on a terminal only)
    ds = open_dataset(out, check_pixels=True)
    assert ds.protocol == "carla-town04@1"
    assert ds.splits == {"train": ("Town01-lane00",), "test": ("Town04-lane03",)}
    scene = ds.scenes["Town04-lane03"]
    assert list(scene.sequences) == ["yaw000", "yaw045"] and len(scene.aerial) == 2
    assert [f.file for f in scene.ground] == [f"ground/{i:06d}.png" for i in range(6)]
    assert scene.meta == {"source": "carla", "town": "Town04", "lane": 3}
    f = 1000.0 / (2**24 - 1)
    by_image = {}
    for rec in json.loads((src / "capture.json").read_text())["frames"]:
        by_image[(f"{rec['town']}-lane{rec['lane']:02d}", rec.get("sequence") or f"yaw{rec.get('yaw_offset_deg', 0):03d}",
                  rec["kind"], rec.get("index"), rec["location"][0])] = rec["image"]
    for name, sc in ds.scenes.items():
        for fr in sc.ground:
            key = next(k for k in by_image if k[0] == name and k[1] == fr.sequence and k[2] == "ground" and k[3] == fr.index)
            t = truth[by_image[key]]
            fwd, right = _carla_forward_right(*t["rot"])
            np.testing.assert_allclose(fr.camera().forward, fwd, atol=1e-12)
            np.testing.assert_allclose(fr.c2w[:3, 0], right, atol=1e-12)
            np.testing.assert_allclose(fr.camera().center, np.array(t["loc"]) * [1, -1, 1])
            np.testing.assert_allclose(fr.camera().K, [[4, 0, 4], [0, 4, 3], [0, 0, 1]])  # f = 8 / (2 tan 45)
            np.testing.assert_array_equal(imagefiles.read_image_uint8(fr.path), t["rgb"])  # RGB kept, alpha dropped
            d = fr.depth()
            expect = (t["code"] * f).astype(np.float32)
            expect[0, 0] = np.inf
            np.testing.assert_array_equal(d, expect)
    # sequence index order follows 'index', not the order in capture.json
    xs = [fr.camera().center[0] for fr in scene.sequences["yaw045"]]
    assert xs == [10.0, 12.0, 14.0]


def test_import_carla_refuses_existing_out(carla_src, tmp_path):
    src, _ = carla_src
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    _, _, err = run_cli("data", "import-carla", str(src), str(out), "--no-progress", check=2)
    assert err.strip() == f"skyeyes-bench: error: {out}: already exists; pass --force to replace it"
    assert os.listdir(out) == ["keep.txt"]
    # --force replaces an earlier dataset (or an empty folder) only, never a folder of other files
    _, _, err = run_cli("data", "import-carla", str(src), str(out), "--no-progress", "--force", check=2)
    assert err.strip() == (f"skyeyes-bench: error: {out}: exists and is not a dataset folder (--force replaces "
                           "only a dataset folder written earlier); move it away or choose another path")
    assert os.listdir(out) == ["keep.txt"]
    (out / "keep.txt").unlink()
    for _ in range(2):  # the empty folder, then the dataset written into it
        run_cli("data", "import-carla", str(src), str(out), "--no-progress", "--force")
        assert (out / "dataset.json").is_file()


def _mutate_capture(src: Path, fn):
    p = src / "capture.json"
    raw = json.loads(p.read_text())
    fn(raw)
    p.write_text(json.dumps(raw))
    return p


@pytest.mark.parametrize(
    "mutate, expect",
    [
        (lambda r: r["frames"][1].pop("rotation"), "frames[1].rotation: missing (expected [pitch, yaw, roll] in degrees (3 finite numbers))"),
        (lambda r: r["frames"][2].update(location=[1, 2, "z"]), "frames[2].location: expected [x, y, z] in CARLA metres"),
        (lambda r: r["frames"][0].update(fov=180), "frames[0].fov: expected the horizontal field of view"),
        (lambda r: r["frames"][3].update(kind="street"), "frames[3].kind: expected 'ground' or 'aerial'"),
        (lambda r: r["frames"][4].update(image="rgb/missing.png"), "frames[4].image: RGB image"),
        (lambda r: r["frames"][5].update(width=9), "is 8x6, expected 9x6 (fields 'width', 'height')"),
        (lambda r: r["frames"][0].update(colour=1), "frames[0].colour: unknown field"),
        (lambda r: r["frames"][0].update(index=7), "sequence 'yaw000' has missing index 2"),
        (lambda r: r["frames"][0].update(town="Town99"), "town 'Town99' is in neither the train"),
        (lambda r: r["frames"][0].update(lane=-1), "frames[0].lane: expected the lane number"),
        (lambda r: r.update(format="other"), "capture.json: field 'format': expected 'skyeyes-carla-capture'"),
        (lambda r: r["frames"][0].pop("yaw_offset_deg"), "frames[0]: a ground frame needs 'yaw_offset_deg'"),
    ],
)
def test_import_carla_bad_input(carla_src, tmp_path, mutate, expect):
    src, _ = carla_src
    p = _mutate_capture(src, mutate)
    out = tmp_path / "work" / "out"
    out.parent.mkdir()
    _, stdout, err = run_cli("data", "import-carla", str(src), str(out), "--no-progress", check=2)
    assert expect in err, err
    assert err.count("\n") == 1 and "Traceback" not in err
    if "frames[" in expect or "format" in expect:
        assert str(p) in err
    assert os.listdir(out.parent) == []  # nothing written, no temporary left


def test_import_carla_bad_depth_and_image_files(carla_src, tmp_path):
    src, _ = carla_src
    data = (src / "depth" / "000001.png").read_bytes()
    (src / "depth" / "000001.png").write_bytes(data[: len(data) // 2])  # truncated: found while writing
    out = tmp_path / "work" / "out"
    out.parent.mkdir()
    _, _, err = run_cli("data", "import-carla", str(src), str(out), "--no-progress", check=2)
    assert f"{src / 'depth' / '000001.png'}: cannot decode image" in err and err.count("\n") == 1
    assert os.listdir(out.parent) == []
    _, _, err = run_cli("data", "import-carla", str(tmp_path / "nope"), str(out), check=2)
    assert "not a folder" in err


def test_import_carla_unknown_town_with_split(carla_src, tmp_path):
    src, _ = carla_src
    _mutate_capture(src, lambda r: [f.update(town="Town10HD") for f in r["frames"] if f["town"] == "Town01"])
    run_cli("data", "import-carla", str(src), str(tmp_path / "o"), "--split", "train", "--no-progress")
    assert open_dataset(tmp_path / "o").splits["train"] == ("Town10HD-lane00",)



def _mc_import(src, out, *extra, check=0):
    return run_cli("data", "import-matrixcity", str(src), str(out), "--town", "region5", "--no-progress", *extra,
                   check=check)


@pytest.mark.parametrize("paper, face_major", [(False, False), (True, False), (False, True)])
def test_import_matrixcity(tmp_path, paper, face_major):
    src = tmp_path / "mc"
    truth = make_matrixcity(src, paper=paper, face_major=face_major)
    out = tmp_path / "out"
    _, stdout, _ = _mc_import(src, out)
    assert stdout.splitlines()[0] == f"wrote {out}: 2 scenes, 8 sequences, 28 ground frames, 2 aerial frames"
    ds = open_dataset(out, check_pixels=True)
    assert ds.protocol == "citysample-region5@1" and ds.splits == {"train": (), "test": ("region5-lane00", "region5-lane01")}
    meta = ds.meta
    assert meta["pose_format"] == ("paper" if paper else "raw")
    assert meta["source_step_m"] == pytest.approx(1.0) and meta["step_m"] == pytest.approx(2.0)
    diffs = " | ".join(meta["protocol_differences"])
    assert "resampled from 1.00 m to 2.00 m" in diffs and "24 non-horizontal street frames" in diffs
    assert "yaw offsets ['yaw000', 'yaw090', 'yaw180', 'yaw270']" in diffs
    assert "image sizes 8x6 (protocol: 512x512)" in diffs and "horizontal fov" not in diffs
    a, b = ds.scenes["region5-lane00"], ds.scenes["region5-lane01"]
    assert list(a.sequences) == list(b.sequences) == ["yaw000", "yaw090", "yaw180", "yaw270"]
    assert [len(q) for q in a.sequences.values()] == [4] * 4  # x = 0, 2, 4, 6
    assert [len(q) for q in b.sequences.values()] == [3] * 4  # y = 50, 52, 54
    # lane 0 drives along +x: yaw000 looks along +x; lane 1 drives along +y: its yaw000 looks along +y
    for fr in a.sequences["yaw000"]:
        np.testing.assert_allclose(fr.camera().forward, [1, 0, 0], atol=1e-5)
    for fr in b.sequences["yaw000"]:
        np.testing.assert_allclose(fr.camera().forward, [0, 1, 0], atol=1e-5)
    for fr in b.sequences["yaw090"]:  # 90 deg to the left of +y is -x
        np.testing.assert_allclose(fr.camera().forward, [-1, 0, 0], atol=1e-5)
    np.testing.assert_allclose([fr.camera().center[0] for fr in a.sequences["yaw270"]], [0, 2, 4, 6], atol=1e-5)
    # poses, pixels and depth against what the fixture wrote
    road = {tuple(np.round(t["c2w"][:3, 3], 3)) + tuple(np.round(t["c2w"][:3, 2], 3)): t
            for (folder, _), t in truth.items() if folder == "road_a"}
    for fr in [*a.ground, *b.ground]:
        t = road[tuple(np.round(fr.c2w[:3, 3], 3)) + tuple(np.round(fr.c2w[:3, 2], 3))]
        np.testing.assert_allclose(fr.c2w, t["c2w"], atol=1e-5)
        np.testing.assert_array_equal(imagefiles.read_image_uint8(fr.path), t["rgb"])
        np.testing.assert_allclose(fr.depth(), t["depth_m"], rtol=1e-6)
        assert np.isinf(fr.depth()[1, 2])
        np.testing.assert_allclose(fr.camera().K, [[4, 0, 4], [0, 4, 3], [0, 0, 1]], atol=1e-9)
    # the two aerial views over lane 0 are attached to it, the far one to nothing
    assert len(a.aerial) == 2 and len(b.aerial) == 0
    assert all(np.linalg.norm(fr.camera().center[:2] - [1000, 1000]) > 1 for s in ds.scenes.values() for fr in s.aerial)


def test_import_matrixcity_5m_step_kept(tmp_path):
    src = tmp_path / "mc"
    make_matrixcity(src, step=3.0, depth=False)  # 3 m: no whole number of steps makes 2 m
    out = tmp_path / "out"
    _, stdout, _ = _mc_import(src, out)
    meta = open_dataset(out).meta
    assert meta["step_m"] == pytest.approx(3.0)
    assert "ground step 3.00 m kept (no whole number of source steps makes 2 m)" in meta["protocol_differences"]
    assert "differs from the protocol: ground step 3.00 m kept" in stdout


def test_import_matrixcity_bad_input(tmp_path):
    src = tmp_path / "mc"
    make_matrixcity(src, depth=False)
    out = tmp_path / "work" / "out"
    out.parent.mkdir()
    tj = src / "street" / "train" / "road_a" / "transforms.json"
    raw = json.loads(tj.read_text())
    del raw["frames"][3]["rot_mat"]
    tj.write_text(json.dumps(raw))
    _, _, err = _mc_import(src, out, check=2)
    assert f"{tj}: frames[3].rot_mat: missing (expected a pose matrix (4x4 finite numbers))" in err and err.count("\n") == 1
    # a raw file read as paper: the rotation is not orthonormal
    _, _, err = _mc_import(src, out, "--pose-format", "paper", check=2)
    assert "no transforms_*.json found" in err
    raw["frames"][3]["rot_mat"] = (np.eye(4) * 0.01).tolist()
    raw["frames"][3]["rot_mat"][3][3] = 1.0
    raw["frames"][4]["rot_mat"] = np.diag([0.02, 0.01, 0.01, 1.0]).tolist()
    tj.write_text(json.dumps(raw))
    _, _, err = _mc_import(src, out, check=2)
    assert f"{tj}: frames[4].rot_mat: MatrixCity pose (raw): rotation is not orthonormal" in err
    assert "--pose-format raw" in err
    raw["frames"][4]["rot_mat"] = raw["frames"][3]["rot_mat"]
    tj.write_text(json.dumps(raw))
    (src / "street" / "train" / "road_a" / "0005.png").unlink()
    _, _, err = _mc_import(src, out, check=2)
    assert f"{tj}: frames[5].frame_index: image" in err and "0005.png not found" in err
    assert os.listdir(out.parent) == []
    _, _, err = _mc_import(src, out, "--town", "region 5", check=2)
    assert "--town: expected a town name" in err


def test_import_matrixcity_town_split(tmp_path):
    src = tmp_path / "mc"
    make_matrixcity(src, depth=False)
    _, _, err = run_cli("data", "import-matrixcity", str(src), str(tmp_path / "o"), "--no-progress", check=2)
    assert "town 'matrixcity' is in neither the train" in err and "pass --split train|test" in err
    _mc_import(src, tmp_path / "o2", "--town", "region1")
    assert open_dataset(tmp_path / "o2").splits["train"] == ("region1-lane00", "region1-lane01")


# --------------------------------------------------------------------------- pure helpers


def test_split_lanes():
    track = np.array([[x, 0, 0] for x in range(5)] + [[4, y, 0] for y in range(1, 4)]  # corner at (4, 0)
                     + [[50, 50, 0], [51, 50, 0]], dtype=float)  # jump
    lanes = split_lanes(track)
    assert [list(lane) for lane in lanes] == [[0, 1, 2, 3, 4], [5, 6, 7], [8, 9]]
    assert split_lanes(track[:1]) == []


def test_resample_step():
    assert resample_step(1.0, 2.0) == 2
    assert resample_step(2.0, 2.0) == 1
    assert resample_step(0.5, 2.0) == 4
    assert resample_step(5.0, 2.0) is None
    assert resample_step(3.0, 2.0) is None


def _png_rgba(path: Path, px: np.ndarray):
    """A plain RGBA PNG written with zlib (independent of OpenImageIO)."""
    import struct
    import zlib

    h, w, _ = px.shape
    raw = b"".join(b"\x00" + px[i].tobytes() for i in range(h))

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 6, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def test_rgba_png_colour_not_premultiplied(tmp_path):
    px = np.random.default_rng(0).integers(0, 256, (H, W, 4), dtype=np.uint8)
    px[..., 3] = 100  # translucent: RGB must still come back as stored
    _png_rgba(tmp_path / "a.png", px)
    np.testing.assert_array_equal(imagefiles.read_image_uint8(tmp_path / "a.png"), px)
    np.testing.assert_array_equal(np.rint(imagefiles.read_image(tmp_path / "a.png") * 255), px[..., :3])


@pytest.mark.parametrize("field, value", [("image", "ABS"), ("image", "../outside.png"), ("depth", "ABS"),
                                          ("image", "rgb/link.png")])
def test_import_carla_refuses_paths_leaving_the_capture(carla_src, tmp_path, field, value):
    """An absolute path, '..' or a symlink out of the capture folder: one line naming the field."""
    src, _ = carla_src
    outside = tmp_path / "outside.png"
    outside.write_bytes((src / "rgb" / "000000.png").read_bytes())
    (src / "rgb" / "link.png").symlink_to(outside)
    value = str(outside) if value == "ABS" else value
    _mutate_capture(src, lambda r: r["frames"][0].update({field: value}))
    out = tmp_path / "work" / "out"
    out.parent.mkdir()
    _, _, err = run_cli("data", "import-carla", str(src), str(out), "--no-progress", check=2)
    assert f"capture.json: frames[0].{field}: " in err and f"{value!r} leaves {src}" in err, err
    assert err.count("\n") == 1 and os.listdir(out.parent) == []
