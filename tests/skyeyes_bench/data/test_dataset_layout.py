"""Canonical dataset layout: write, reopen, lazy loading, every validation problem, `data check`."""

import json
import os
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli

from skyeyes_bench import imagefiles
from skyeyes_bench.cameras import Camera
from skyeyes_bench.data.layout import open_dataset, validate_dataset
from skyeyes_bench.data.writer import DatasetWriter
from skyeyes_bench.errors import UserError, ValidationError

W, H = 16, 12


def _intr(w=W, h=H, f=10.0):
    return {"width": w, "height": h, "fx": f, "fy": f, "cx": w / 2, "cy": h / 2}


def _img(seed):
    return np.random.default_rng(seed).random((H, W, 3)).astype(np.float32)


def _depth(seed):
    d = np.random.default_rng(seed).uniform(0.5, 80, (H, W)).astype(np.float32)
    d[0, :3] = np.inf  # sky
    return d


def make_dataset(root: Path, *, scenes=("test-0-lane00", "train-0-lane00"), seqs=("yaw000", "yaw045"),
                 n=3, depth=True) -> Path:
    with DatasetWriter(root, name="tiny", protocol="synthtown@1") as w:
        for si, name in enumerate(scenes):
            s = w.scene(name, {"ground": _intr(), "aerial": _intr()}, meta={"lane": si})
            for a in range(2):
                cam = Camera.from_ypr((0, 2 * a, 52), 0, -45, fov_deg=77, width=W, height=H)
                s.add_aerial(_img(100 + a), cam.c2w)
            for k, seq in enumerate(seqs):
                for i in range(n):
                    cam = Camera.from_ypr((2 * i, 0, 2), 45 * k, 0, fov_deg=77, width=W, height=H)
                    s.add_ground(_img(10 * k + i), cam.c2w, sequence=seq, index=i,
                                 depth=_depth(i) if depth else None)
            s.close()
        w.finish(splits={"test": [scenes[0]], "train": list(scenes[1:])}, meta={"note": "test"})
    return root


@pytest.fixture
def ds_root(tmp_path) -> Path:
    return make_dataset(tmp_path / "ds")


def _scene_json(root: Path, scene="test-0-lane00") -> tuple[Path, dict]:
    p = root / scene / "scene.json"
    return p, json.loads(p.read_text())


def _problems(root) -> list[str]:
    ds, problems = validate_dataset(root, check_pixels=True)
    assert (ds is None) == bool(problems)
    return problems


def test_write_and_reopen(ds_root):
    ds = open_dataset(ds_root)
    assert ds.name == "tiny" and ds.protocol == "synthtown@1" and ds.meta == {"note": "test"}
    assert ds.splits == {"test": ("test-0-lane00",), "train": ("train-0-lane00",)}
    scene = ds.scenes["test-0-lane00"]
    assert scene.meta == {"lane": 0}
    assert [f.file for f in scene.ground] == [f"ground/{i:06d}.png" for i in range(6)]  # running counter
    assert [f.file for f in scene.aerial] == ["aerial/000000.png", "aerial/000001.png"]
    assert list(scene.sequences) == ["yaw000", "yaw045"]
    seq = scene.sequences["yaw045"]
    assert seq.id == "test-0-lane00/yaw045" and len(seq) == 3 and [f.index for f in seq] == [0, 1, 2]
    f = seq.frames[1]
    expect = Camera.from_ypr((2, 0, 2), 45, 0, fov_deg=77, width=W, height=H)
    np.testing.assert_allclose(f.c2w, expect.c2w)
    np.testing.assert_allclose(f.camera().K, [[10, 0, 8], [0, 10, 6], [0, 0, 1]])
    img = f.image()
    assert img.dtype == np.float32 and img.shape == (H, W, 3)
    np.testing.assert_array_equal(np.rint(img * 255), np.rint(_img(11) * 255))  # 8-bit quantised
    d = f.depth()
    assert d.dtype == np.float32 and d.shape == (H, W)
    np.testing.assert_array_equal(d, _depth(1))  # float32 EXR is lossless, inf kept
    assert np.isinf(d[0, 0]) and f.semantics() is None
    assert scene.aerial[0].depth() is None
    assert [s.name for s in ds.split("test")] == ["test-0-lane00"]
    assert [q.id for q in ds.sequences("train")] == ["train-0-lane00/yaw000", "train-0-lane00/yaw045"]
    with pytest.raises(UserError, match="no split 'val'"):
        ds.split("val")


def test_lazy_loading(ds_root, monkeypatch):
    calls = []
    real = imagefiles.read_image
    monkeypatch.setattr(imagefiles, "read_image", lambda p: calls.append(p) or real(p))
    ds = open_dataset(ds_root)
    assert calls == []  # opening reads headers only
    ds.scenes["test-0-lane00"].ground[2].image()
    assert len(calls) == 1 and str(calls[0]).endswith("test-0-lane00/ground/000002.png")


def test_depth_exr_round_trip_through_file(tmp_path):
    d = np.random.default_rng(0).uniform(0, 1000, (37, 53)).astype(np.float32)
    d[5, 7], d[0, 0], d[-1, -1] = np.inf, 0.0, 1e-6
    imagefiles.write_depth(tmp_path / "d.exr", d)
    back = imagefiles.read_depth(tmp_path / "d.exr")
    np.testing.assert_array_equal(back, d)  # exact, not scrambled (OpenImageIO scrambles a 1-channel image given as [H, W])
    # read independently of our reader: OpenImageIO directly
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(tmp_path / "d.exr"))
    assert buf.spec().nchannels == 1 and str(buf.spec().format) == "float"
    np.testing.assert_array_equal(buf.get_pixels(oiio.FLOAT)[..., 0], d)


def test_summary(ds_root):
    s = open_dataset(ds_root).summary()
    assert s["splits"]["test"] == {"scenes": 1, "sequences": 2, "ground_frames": 6, "aerial_frames": 2}
    assert s["resolution"] == {"aerial": "16x12", "ground": "16x12"}
    assert s["sequence_length"] == {"min": 3, "max": 3}
    assert s["layers"]["ground_depth"] is True and s["layers"]["aerial_depth"] is False
    p, raw = _scene_json(ds_root)
    raw["ground"][1]["intrinsics"] = _intr(32, 24)  # one frame of another size (image too)
    p.write_text(json.dumps(raw))
    imagefiles.write_image(ds_root / "test-0-lane00" / raw["ground"][1]["file"], np.zeros((24, 32, 3)))
    imagefiles.write_depth(ds_root / "test-0-lane00" / "ground_depth" / "000001.exr", np.ones((24, 32)))
    assert open_dataset(ds_root).summary()["resolution"] == {"aerial": "16x12", "ground": "16x12, 32x24"}


def test_data_check_cli(ds_root):
    _, out, err = run_cli("data", "check", str(ds_root))
    assert "dataset 'tiny'  protocol synthtown@1" in out
    assert "  test      1 scenes     2 sequences       6 ground frames      2 aerial frames\n" in out
    assert "resolution: aerial 16x12, ground 16x12" in out
    assert "optional layers: ground_depth" in out and out.rstrip().endswith("OK")
    _, out, _ = run_cli("data", "check", str(ds_root), "--json")
    assert json.loads(out)["splits"]["train"]["ground_frames"] == 6


def test_data_check_cli_invalid(ds_root, tmp_path):
    (ds_root / "test-0-lane00" / "ground" / "000001.png").unlink()
    rc, out, err = run_cli("data", "check", str(ds_root), check=2)
    assert out == "" and "Traceback" not in err
    assert err.startswith("skyeyes-bench: error: ") and "000001.png: missing file" in err
    rc, out, err = run_cli("data", "check", str(tmp_path / "nothing"), check=2)
    assert err.strip() == f"skyeyes-bench: error: {tmp_path / 'nothing'}: not a folder"


def test_missing_and_truncated_images(ds_root):
    g = ds_root / "test-0-lane00" / "ground"
    (g / "000000.png").unlink()
    data = (g / "000001.png").read_bytes()
    (g / "000001.png").write_bytes(data[: len(data) // 2])  # header intact, pixels cut
    (g / "000002.png").write_bytes(data[:20])  # header cut
    (ds_root / "test-0-lane00" / "ground_depth" / "000003.exr").unlink()
    problems = _problems(ds_root)
    joined = "\n".join(problems)
    assert f"{g / '000000.png'}: missing file" in problems
    assert any(p.startswith(f"{g / '000001.png'}: cannot decode image") for p in problems), joined
    assert any(p.startswith(f"{g / '000002.png'}: cannot open image") for p in problems), joined
    assert any(p.startswith(f"{ds_root / 'test-0-lane00' / 'ground_depth' / '000003.exr'}: missing") for p in problems)
    assert len(problems) == 4 and all("\n" not in p for p in problems)
    # headers only (what open_dataset does by default) still find the cut header
    _, quick = validate_dataset(ds_root)
    assert len(quick) == 3
    rc, _, err = run_cli("data", "check", str(ds_root), check=2)
    assert "4 problems" in err


@pytest.mark.parametrize(
    "mutate, expect",
    [
        (lambda m: np.diag([1.1, 1.1, 1.1, 1.0]) @ m, "field 'c2w' is not a rigid transform: rotation is not orthonormal"),
        (lambda m: np.diag([1.0, -1.0, 1.0, 1.0]) @ m, "field 'c2w' is not a rigid transform: rotation has det -1.000"),
        # NaN is not JSON: the one reader refuses it, naming the element
        (lambda m: np.where(np.eye(4, dtype=bool), np.nan, m), "field 'ground[4].c2w[0][0]' is nan"),
        (lambda m: np.vstack([m[:3], [[0, 0, 1, 1]]]), "last row"),
        (lambda m: m[:3], "field 'c2w': expected a camera-to-world matrix (4x4 finite numbers)"),
        (lambda m: m.astype(str), "field 'c2w': expected a camera-to-world matrix (4x4 finite numbers), got [['"),
    ],
)
def test_non_rigid_pose(ds_root, mutate, expect):
    p, raw = _scene_json(ds_root)
    raw["ground"][4]["c2w"] = mutate(np.array(raw["ground"][4]["c2w"])).tolist()
    p.write_text(json.dumps(raw))
    problems = _problems(ds_root)
    assert len(problems) == 1
    assert problems[0].startswith(f"{p}: ") and "ground[4]" in problems[0] and expect in problems[0], problems


def test_intrinsics_must_fit_image(ds_root):
    p, raw = _scene_json(ds_root)
    raw["intrinsics"]["aerial"]["width"] = 20  # images are 16 wide
    raw["ground"][0]["intrinsics"] = {**_intr(), "cx": 30.0}  # principal point outside
    p.write_text(json.dumps(raw))
    problems = _problems(ds_root)
    a = ds_root / "test-0-lane00" / "aerial"
    assert f"{a / '000000.png'}: image is 16x12, intrinsics say 20x12" in problems
    assert f"{a / '000001.png'}: image is 16x12, intrinsics say 20x12" in problems
    assert any("ground[0] (ground/000000.png) field 'intrinsics': principal point (30.0, 6.0) lies outside" in q
               for q in problems), problems
    assert len(problems) == 3  # the dropped frame's hole in yaw000 is not reported again


def test_sequence_gaps_and_duplicates(ds_root):
    p, raw = _scene_json(ds_root)
    raw["ground"][2]["index"] = 7  # yaw000: 0, 1, 7
    raw["ground"][4]["index"] = 0  # yaw045: 0, 0, 2
    p.write_text(json.dumps(raw))
    problems = _problems(ds_root)
    assert f"{p}: sequence 'yaw000' is not numbered 0..n-1 (missing indices [2, 3, 4, 5, 6]; field 'index')" in problems
    assert f"{p}: sequence 'yaw045' is not numbered 0..n-1 (duplicate indices [0]; missing indices [1]; field 'index')" in problems
    assert len(problems) == 2


def test_frame_fields(ds_root):
    p, raw = _scene_json(ds_root)
    del raw["ground"][0]["sequence"]
    raw["ground"][1]["index"] = -1
    del raw["ground"][3]["c2w"]
    raw["ground"][4]["file"] = "../escape.png"
    raw["aerial"][1]["file"] = raw["aerial"][0]["file"]
    p.write_text(json.dumps(raw))
    problems = _problems(ds_root)
    joined = "\n".join(problems)
    assert "ground[0] (ground/000000.png): field 'sequence': missing (expected a sequence name (a plain name" in joined
    assert "ground[1] (ground/000001.png): field 'index': expected the frame's position in its sequence (an integer >= 0), got -1" in joined
    assert "ground[3] (ground/000003.png): field 'c2w' missing" in joined
    assert "ground[4] field 'file': expected the image file within the scene folder (a relative path of plain names such as 'ground/000012.png'), got '../escape.png'" in joined
    assert "aerial[1] (aerial/000000.png): field 'file' repeats aerial[0]'s file" in joined


def test_splits_and_dataset_fields(ds_root):
    dfile = ds_root / "dataset.json"
    raw = json.loads(dfile.read_text())
    raw["splits"]["test"] = ["test-0-lane00", "Town04-lane99"]
    raw["splits"]["val"] = ["test-0-lane00"]
    raw["protocol"] = "synthtown"
    dfile.write_text(json.dumps(raw))
    problems = _problems(ds_root)
    assert f"{dfile}: split 'test' names unknown scene 'Town04-lane99' (field 'splits.test')" in problems
    assert f"{dfile}: scene 'test-0-lane00' is in both split 'test' and split 'val'" in problems
    assert any("field 'protocol' is 'synthtown', expected '<id>@<N>'" in q for q in problems)
    assert len(problems) == 3
    dfile.write_text("{not json")
    assert _problems(ds_root)[0].startswith(f"{dfile}: not valid JSON (line 1")
    dfile.write_text(json.dumps({"name": "x", "protocol": "a@1", "splits": {}}))
    assert _problems(ds_root) == [f"{dfile}: field 'scenes' missing or not a list"]


def test_missing_scene_json(ds_root):
    (ds_root / "train-0-lane00" / "scene.json").unlink()
    assert _problems(ds_root) == [
        f"{ds_root / 'train-0-lane00' / 'scene.json'}: missing (scene 'train-0-lane00' is listed in dataset.json)"]


def test_many_problems_listed_at_once(ds_root):
    (ds_root / "test-0-lane00" / "aerial" / "000000.png").unlink()
    p, raw = _scene_json(ds_root, "train-0-lane00")
    raw["ground"][0]["c2w"][0][0] = 5.0
    raw["ground"][5]["index"] = 9  # yaw045: 0, 1, 9
    p.write_text(json.dumps(raw))
    with pytest.raises(ValidationError) as e:
        open_dataset(ds_root)
    assert len(e.value.problems) == 3  # missing file; non-rigid (its hole not repeated); index 9
    msg = str(e.value)
    assert msg.startswith(f"dataset {ds_root}: 3 problems\n  - ")
    assert msg.count("\n  - ") == 3


def test_writer_is_atomic(tmp_path):
    out = tmp_path / "ds"
    with pytest.raises(RuntimeError, match="boom"):
        with DatasetWriter(out, name="x", protocol="synthtown@1") as w:
            s = w.scene("a-lane00", {"ground": _intr(), "aerial": _intr()})
            s.add_ground(_img(0), np.eye(4), sequence="yaw000", index=0)
            raise RuntimeError("boom")
    assert not out.exists() and os.listdir(tmp_path) == []
    with pytest.raises(RuntimeError, match="without finish"):
        with DatasetWriter(out, name="x", protocol="synthtown@1"):
            pass
    assert os.listdir(tmp_path) == []
    make_dataset(out)
    with pytest.raises(UserError, match="already exists; pass --force"):
        make_dataset(out)
    # validate=True: a dataset with a problem is refused and nothing replaces the old one
    before = (out / "dataset.json").read_text()
    with pytest.raises(ValidationError, match="not numbered"):
        with DatasetWriter(out, name="y", protocol="synthtown@1", overwrite=True, validate=True) as w:
            s = w.scene("a-lane00", {"ground": _intr(), "aerial": _intr()})
            s.add_ground(_img(0), np.eye(4), sequence="yaw000", index=1)
            w.finish(splits={"test": ["a-lane00"]})  # closes the scene itself
    assert (out / "dataset.json").read_text() == before
    assert sorted(os.listdir(tmp_path)) == ["ds"]


# --------------------------------------------------------------------------- layer files hold what their names say


def _write_oiio(path: Path, pixels: np.ndarray, fmt: str, like: str) -> None:
    """`pixels` [H, W, C] written by OpenImageIO in the format of the extension `like`, whatever
    `path`'s own extension says (the file is written under a name with `like`, then renamed)."""
    import OpenImageIO as oiio

    tmp = path.with_name("written" + like)
    h, w, c = pixels.shape
    out = oiio.ImageOutput.create(str(tmp))
    assert out.open(str(tmp), oiio.ImageSpec(w, h, c, fmt)) and out.write_image(np.ascontiguousarray(pixels))
    out.close()
    tmp.replace(path)


# Each writes `p` (a depth file, ground_depth/000002.exr, 16x12) as something else: (how, what the one line says)
_NOT_DEPTH = {
    # metres as millimetres in a 16-bit PNG: OpenImageIO reads any format whatever the name, and
    # gave 0.0153 "metres" for 1000 mm
    "png16": (lambda p: _write_oiio(p, np.full((H, W, 1), 1000, np.uint16), "uint16", ".png"),
              "holds a PNG image, not the OpenEXR its name says"),
    "npy": (lambda p: p.write_bytes(_npy_bytes(np.ones((H, W), np.float32))),
            "holds a NumPy .npy array, not the OpenEXR its name says"),
    "rgb-exr": (lambda p: _write_oiio(p, np.ones((H, W, 3), np.float32), "float", ".exr"),
                "holds 3 channels of float"),
    "half-exr": (lambda p: _write_oiio(p, np.ones((H, W, 1), np.float32), "half", ".exr"),
                 "holds 1 channel of half"),
}


def _npy_bytes(a: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


@pytest.mark.parametrize("case", sorted(_NOT_DEPTH))
def test_depth_file_must_be_what_its_name_says(ds_root, case):
    """docs/formats.md: a depth file is an EXR of 1 float32 channel (planar metres, inf = sky).
    Anything else under that name is refused in one line naming the file, what it holds and what
    was expected, by `data check`, `data check --quick` (headers only) and the reader evaluate uses."""
    write, says = _NOT_DEPTH[case]
    p = ds_root / "test-0-lane00" / "ground_depth" / "000002.exr"
    write(p)
    expected = "expected an OpenEXR file of 1 float32 channel (planar depth in metres, inf = sky)"
    for quick in ((), ("--quick",)):
        rc, out, err = run_cli("data", "check", str(ds_root), *quick, check=2)
        assert out == "" and err.count("\n") == 1, err
        assert err.startswith(f"skyeyes-bench: error: {p}: {says}") and expected in err, err
    frame = open_dataset(ds_root, check_files=False).scenes["test-0-lane00"].ground[2]
    with pytest.raises(UserError, match=expected.replace("(", r"\(").replace(")", r"\)")):
        frame.depth()


def test_semantics_file_must_be_an_8_bit_png(ds_root):
    """docs/formats.md: semantics are 8-bit labels in a PNG; a float EXR or a 16-bit PNG under that
    name would be converted to 0..255 labels silently."""
    scene = ds_root / "test-0-lane00"
    (scene / "ground_semantics").mkdir()
    for i in range(6):
        imagefiles.write_labels(scene / "ground_semantics" / f"{i:06d}.png", np.full((H, W), i, np.uint8))
    assert _problems(ds_root) == []
    p = scene / "ground_semantics" / "000004.png"
    _write_oiio(p, np.full((H, W, 1), 3.0, np.float32), "float", ".exr")
    rc, out, err = run_cli("data", "check", str(ds_root), check=2)
    assert err.count("\n") == 1 and err.startswith(f"skyeyes-bench: error: {p}: holds an OpenEXR image, not the PNG its name says")
    assert "expected an 8-bit PNG of labels" in err, err
    _write_oiio(p, np.full((H, W, 1), 3, np.uint16), "uint16", ".png")
    rc, out, err = run_cli("data", "check", str(ds_root), "--quick", check=2)
    assert err.strip() == f"skyeyes-bench: error: {p}: holds 1 channel of uint16, expected an 8-bit PNG of labels"


def test_invalid_depth_values_are_data_not_errors(ds_root):
    """docs/metrics.md ("Depth values"): 0, negative, NaN and -inf are invalid pixels (never seen,
    never part of a warp), +inf is sky; so a depth file holding them is a valid dataset."""
    p = ds_root / "test-0-lane00" / "ground_depth" / "000002.exr"
    d = _depth(2)
    d[1, :4] = [0.0, -3.0, np.nan, -np.inf]
    imagefiles.write_depth(p, d)
    run_cli("data", "check", str(ds_root))
    back = open_dataset(ds_root).scenes["test-0-lane00"].ground[2].depth()
    np.testing.assert_array_equal(back, d)
