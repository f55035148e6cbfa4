"""SynthTown's validation data (`data synthtown --split val`, `presets.for_split`) and its stiff
town (`town.STIFF`: tilted in the world, a cloudy sky), against closed forms and hand-written
expectations: the test data stays what it was, the tilted street is a plane through the origin,
and the cloudy sky is no smooth function of the direction."""

import dataclasses
import json

import numpy as np
import pytest
from conftest import run_cli

from skyeyes_bench.cameras import Camera
from skyeyes_bench.data.synthtown import town as tw
from skyeyes_bench.data.synthtown.generate import dataset_name, get_preset, lane_cameras, town_role
from skyeyes_bench.data.synthtown.presets import PRESETS, for_split
from skyeyes_bench.data.synthtown.render import LABELS, Scene, render
from skyeyes_bench.errors import UserError

ROAD, SKY = LABELS.index("road"), LABELS.index("sky")
assert (ROAD, SKY) == (1, 0)


@pytest.fixture(scope="module")
def smoke_val(tmp_path_factory):
    """(the cache, the CLI's stdout) of `data synthtown --preset smoke --split val` into a cache of its own."""
    cache = tmp_path_factory.mktemp("cache-val")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SKYEYES_CACHE", str(cache))
        rc, out, err = run_cli("data", "synthtown", "--preset", "smoke", "--split", "val", "--quiet")
    return cache, out


# --------------------------------------------------------------------------- the validation data


def test_val_data_holds_the_train_town_and_the_validation_town(smoke_val):
    cache, out = smoke_val
    root = cache / "data" / "synthtown-smoke-val"
    assert out.strip() == f"wrote {root}"
    doc = json.loads((root / "dataset.json").read_text())
    assert doc["name"] == "synthtown-smoke-val"
    assert doc["protocol"] == "synthtown@1"
    assert doc["splits"] == {"train": ["train-0-lane00"], "val": ["val-0-lane00"]}
    assert list(doc["splits"]) == ["train", "val"]
    assert doc["scenes"] == ["train-0-lane00", "val-0-lane00"]
    assert doc["meta"]["official"] is False
    meta = json.loads((root / "val-0-lane00" / "scene.json").read_text())["meta"]
    assert meta["town"] == "val-0"
    assert sorted((root / "val-0-lane00" / "ground").iterdir()) and len(list((root / "val-0-lane00" / "ground").iterdir())) == 8 * 16


def test_val_data_trains_on_the_test_datas_train_frames(smoke_val, synthtown_smoke):
    """The same train town, lanes and frames, byte for byte: a run on val fits what a run on test fits."""
    cache, _ = smoke_val
    a, b = synthtown_smoke / "train-0-lane00", cache / "data" / "synthtown-smoke-val" / "train-0-lane00"
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file() and p.name != "scene.json")
    assert len(files) > 100 and files == sorted(p.relative_to(b) for p in b.rglob("*")
                                                if p.is_file() and p.name != "scene.json")
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
    sa, sb = (json.loads((d / "scene.json").read_text()) for d in (a, b))
    assert sa["aerial"] == sb["aerial"] and sa["ground"] == sb["ground"] and sa["intrinsics"] == sb["intrinsics"]


def test_the_test_data_has_no_val_split(synthtown_smoke):
    doc = json.loads((synthtown_smoke / "dataset.json").read_text())
    assert doc["name"] == "synthtown-smoke"
    assert doc["splits"] == {"train": ["train-0-lane00"], "test": ["test-0-lane00"]}
    assert list(doc["splits"]) == ["train", "test"]
    assert doc["scenes"] == ["train-0-lane00", "test-0-lane00"]


@pytest.mark.parametrize("name", ["test-0", "train-0", "train-1", "val-0"])
def test_every_town_but_the_stiff_ones_is_level_under_a_clear_sky(name):
    t = tw.make_town(name, 0, (3, 3))
    assert t.world is None and t.clouds == 0
    p = np.array([[1.5, -2.0, 3.0]])
    assert np.array_equal(t.to_world(p), p)


def test_the_validation_town_is_a_town_of_its_own():
    a, b = tw.make_town("test-0", 0, (3, 3)), tw.make_town("val-0", 0, (3, 3))
    assert a.box_lo.shape != b.box_lo.shape or not np.array_equal(a.box_lo, b.box_lo)
    assert not np.array_equal(a.sun, b.sun)


def test_presets_for_the_validation_split():
    smoke = PRESETS["smoke"]
    assert for_split(smoke, "test") is smoke
    v = for_split(smoke, "val")
    assert (v.name, v.dataset, v.official, v.protocol) == ("smoke-val", "synthtown-smoke-val", False, "synthtown@1")
    assert v.lanes == (("train-0", 1), ("val-0", 1))
    assert (v.width, v.height, v.frames, v.aa) == (48, 48, 16, 1)
    small = for_split(PRESETS["small"], "val")
    assert small.lanes == (("train-0", 2), ("train-1", 2), ("val-0", 8)) and small.dataset == "synthtown-v2-small-val"
    assert dataset_name("small", 0, "val") == "synthtown-v2-small-val"
    assert dataset_name("small", 3, "val") == "synthtown-v2-small-val-seed3"
    assert dataset_name("small", 0) == "synthtown-v2-small"
    assert [town_role(n) for n in ("train-0", "train-1", "val-0", "test-0", "stiff-0")] == \
        ["train", "train", "val", "test", "test"]
    with pytest.raises(ValueError):
        for_split(smoke, "train")
    with pytest.raises(UserError, match="split 'train'"):
        get_preset("smoke", "train")


def test_the_stiff_protocol_has_no_validation_data(tmp_path):
    with pytest.raises(UserError, match="no validation split"):
        get_preset("small-stiff", "val")
    rc, out, err = run_cli("data", "synthtown", "--preset", "small-stiff", "--split", "val", "--out",
                           str(tmp_path / "x"), check=2)
    assert err.count("\n") == 1 and "small-stiff" in err and "Traceback" not in err
    assert not (tmp_path / "x").exists()


# --------------------------------------------------------------------------- the stiff town


@pytest.fixture(scope="module")
def stiff():
    return tw.make_town("stiff-0", 0, (3, 3))


def test_the_stiff_town_is_tilted_5_degrees_about_a_horizontal_axis(stiff):
    R = stiff.world
    assert R.shape == (3, 3)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    up = R @ np.array([0.0, 0.0, 1.0])
    assert np.degrees(np.arccos(np.clip(up[2], -1, 1))) == pytest.approx(5.0, abs=1e-9)
    # the axis (30 deg from x, horizontal) is left where it is; the town's up leans across it
    axis = np.array([np.cos(np.radians(30)), np.sin(np.radians(30)), 0.0])
    np.testing.assert_allclose(R @ axis, axis, atol=1e-12)
    assert up @ axis == pytest.approx(0.0, abs=1e-12)
    assert stiff.clouds == pytest.approx(0.55)
    # a point of the town goes where the rotation takes it
    np.testing.assert_allclose(stiff.to_world([[0.0, 0.0, 1.0]]), up[None], atol=1e-15)


def test_stiff_ground_cameras_stand_level_above_the_tilted_street(stiff):
    lane = tw.make_lanes(stiff, 1, 16, 2.0, 0)[0]
    p = dataclasses.replace(get_preset("small-stiff"), width=16, height=16, frames=16)
    ground, aerial = lane_cameras(lane, p, stiff)
    assert len(ground) == 8 * 16
    h = np.radians(lane["heading_deg"])
    for seq, i, cam in ground:
        street = np.array([lane["start"][0] + 2.0 * i * np.cos(h), lane["start"][1] + 2.0 * i * np.sin(h), 0.0])
        np.testing.assert_allclose(cam.center, stiff.world @ street + [0, 0, 2.0], atol=1e-9)
        assert cam.forward[2] == pytest.approx(0.0, abs=1e-12)  # pitch 0 in the world
    for i, off, cam in aerial:
        assert np.degrees(np.arcsin(-cam.forward[2])) == pytest.approx(45.0, abs=1e-9)


def test_the_stiff_street_is_the_tilted_plane_through_the_origin(stiff):
    """Road pixels' points (camera centre + unnormalised ray * planar depth) lie on the plane through
    the origin whose normal is the town's up in the world, to float32 depth rounding."""
    lane = tw.make_lanes(stiff, 1, 16, 2.0, 0)[0]
    p = dataclasses.replace(get_preset("small-stiff"), width=32, height=32, frames=16)
    ground, _ = lane_cameras(lane, p, stiff)
    n = stiff.world @ np.array([0.0, 0.0, 1.0])
    checked = 0
    for k in (5, 16 * 2 + 5):  # two yaws of one point
        cam = ground[k][2]
        _, depth, labels = render(Scene.from_town(stiff), cam, aa=1)
        road = (labels == ROAD).ravel()
        o, d = cam.rays(normalize=False)
        z = depth.ravel()[road].astype(np.float64)
        pts = o[road] + d[road] * z[:, None]
        off = pts @ n
        tol = 1e-6 + 4 * np.finfo(np.float32).eps * z * np.abs(d[road] @ n)
        assert (np.abs(off) <= tol).all(), np.abs(off).max()
        # ... and not on the level plane z = 0 (the test sees the tilt)
        assert np.abs(pts[:, 2]).max() > 0.1
        checked += int(road.sum())
    assert checked > 200


def _sky_residual(town, size: int = 32) -> tuple[int, float]:
    """(sky pixels, RMS residual of a degree-2 polynomial of the unit direction fitted to their
    sRGB colour) of a view looking up 30 deg from a lane point, away from the sun."""
    lane = tw.make_lanes(town, 1, 16, 2.0, 0)[0]
    p = dataclasses.replace(get_preset("small-stiff"), width=size, height=size, frames=16)
    centre = lane_cameras(lane, p, town)[0][5][2].center
    away = np.degrees(np.arctan2(town.sun[1], town.sun[0])) + 180.0
    cam = Camera.from_ypr(centre, away, 30.0, fov_deg=90, width=size, height=size)
    rgb, _, labels = render(Scene.from_town(town), cam, aa=1)
    sky = (labels == SKY).ravel()
    _, d = cam.rays()
    x, y, z = d[sky].T
    A = np.stack([np.ones_like(x), x, y, z, x * x, y * y, z * z, x * y, x * z, y * z], 1)
    b = rgb.reshape(-1, 3)[sky].astype(np.float64)
    coef, *_ = np.linalg.lstsq(A, b, rcond=None)
    return int(sky.sum()), float(np.sqrt(((b - A @ coef) ** 2).mean()))


def test_the_stiff_sky_is_no_smooth_function_of_the_direction(stiff):
    n, rms = _sky_residual(stiff)
    assert n > 200
    assert rms > 0.02
    n, rms = _sky_residual(tw.make_town("test-0", 0, (3, 3)))
    assert n > 200
    assert rms < 0.01
