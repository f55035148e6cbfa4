"""skyeyes_bench.splits: the dataset a run on the validation split sees (`scored_view`), and the
split a tool that screens settings may run on (`screening_split`)."""

import dataclasses
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from skyeyes_bench.data.layout import Dataset, Scene
from skyeyes_bench.errors import UserError
from skyeyes_bench.protocol import ValSpec, load_protocol
from skyeyes_bench.splits import check_split, scored_view, screening_split


def _dataset(splits: dict, towns: dict | None = None, root=Path("/data/ds")) -> Dataset:
    """A Dataset of scenes without frames; `towns`: {scene: its meta "town"}."""
    towns = towns or {}
    names = [s for members in splits.values() for s in members]
    scenes = {n: Scene(n, root / n, (), (), {"town": towns[n]} if n in towns else {}) for n in names}
    return Dataset(root, "hand-made", "carla-town04@3", {k: tuple(v) for k, v in splits.items()}, scenes)


def _protocol(towns=("Town05",), source="train", ref="carla-town04@3"):
    """A stand-in for a Protocol: what scored_view reads of one (its ref and val)."""
    return SimpleNamespace(ref=ref, val=ValSpec(towns=tuple(towns), source=source, why="test"))


CARLA = {"Town01-lane00": "Town01", "Town05-lane00": "Town05", "Town03-lane00": "Town03", "Town05-lane01": "Town05",
         "Town04-lane00": "Town04"}
CARLA_SPLITS = {"train": ["Town01-lane00", "Town05-lane00", "Town03-lane00", "Town05-lane01"], "test": ["Town04-lane00"]}


def test_test_is_the_dataset_itself():
    ds = _dataset(CARLA_SPLITS, CARLA)
    assert scored_view(ds, "test", _protocol()) is ds
    assert scored_view(ds, "test") is ds
    assert ds.scored == "test"


def test_a_dataset_with_its_own_val_split():
    ds = _dataset({"train": ["train-0-lane00", "train-1-lane00"], "val": ["val-0-lane01", "val-0-lane00"]})
    for proto in (None, _protocol(("val-0",), "own", "synthtown@4")):
        v = scored_view(ds, "val", proto)
        assert v.splits == {"train": ("train-0-lane00", "train-1-lane00"), "test": ("val-0-lane01", "val-0-lane00")}
        assert v.scored == "val"
        assert [s.name for s in v.split("test")] == ["val-0-lane01", "val-0-lane00"]
        assert v.name == ds.name and v.root == ds.root and v.scenes is ds.scenes
    # the dataset itself is left as it was
    assert ds.scored == "test" and set(ds.splits) == {"train", "val"}


def test_a_val_split_inside_train_is_left_out_of_training():
    ds = _dataset({"train": ["a", "b", "c"], "val": ["b"]})
    v = scored_view(ds, "val")
    assert v.splits == {"train": ("a", "c"), "test": ("b",)}


def test_the_protocols_train_towns_make_the_validation_split():
    ds = _dataset(CARLA_SPLITS, CARLA)
    v = scored_view(ds, "val", _protocol())
    assert v.splits == {"train": ("Town01-lane00", "Town03-lane00"), "test": ("Town05-lane00", "Town05-lane01")}
    assert v.scored == "val"
    # two validation towns
    v = scored_view(ds, "val", _protocol(("Town05", "Town01")))
    assert v.splits == {"train": ("Town03-lane00",), "test": ("Town01-lane00", "Town05-lane00", "Town05-lane01")}


def test_the_builtin_carla_protocol_and_a_dataset_on_disk(tmp_path):
    """The real protocol's val.toml (Town05, source "train") and scene.json's meta.town as written."""
    from skyeyes_bench.data.layout import open_dataset
    from skyeyes_bench.data.writer import DatasetWriter

    intr = {"width": 8, "height": 8, "fx": 4.0, "fy": 4.0, "cx": 4.0, "cy": 4.0}
    img = np.full((8, 8, 3), 0.5, np.float32)
    with DatasetWriter(tmp_path / "ds", name="carla-hand", protocol="carla-town04@3") as w:
        for name, town in CARLA.items():
            s = w.scene(name, {"ground": intr, "aerial": intr}, meta={"town": town})
            s.add_aerial(img, np.eye(4))
            s.add_ground(img, np.eye(4), sequence="yaw000", index=0)
            s.close()
        w.finish(splits=CARLA_SPLITS)
    ds = open_dataset(tmp_path / "ds")
    v = scored_view(ds, "val", load_protocol("carla-town04@3"))
    assert v.splits == {"train": ("Town01-lane00", "Town03-lane00"), "test": ("Town05-lane00", "Town05-lane01")}
    assert [q.id for q in v.sequences("test")] == ["Town05-lane00/yaw000", "Town05-lane01/yaw000"]


@pytest.mark.parametrize("proto", [None, "no-val", "own"])
def test_no_validation_split_anywhere_is_one_line(proto):
    ds = _dataset(CARLA_SPLITS, CARLA)
    p = {None: None, "no-val": SimpleNamespace(ref="carla-town04@3", val=None),
         "own": _protocol(("val-0",), "own", "synthtown@4")}[proto]
    with pytest.raises(UserError) as e:
        scored_view(ds, "val", p)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("/data/ds/dataset.json: ") and "no 'val' split" in msg, msg


def test_no_scene_in_the_validation_towns_is_one_line():
    towns = {**CARLA, "Town05-lane00": "Town02", "Town05-lane01": "Town02"}
    ds = _dataset(CARLA_SPLITS, towns)
    with pytest.raises(UserError) as e:
        scored_view(ds, "val", _protocol())
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("/data/ds/dataset.json: ") and "Town05" in msg and "meta.town" in msg
    # scenes without a town at all: the same
    with pytest.raises(UserError, match="meta.town"):
        scored_view(_dataset(CARLA_SPLITS), "val", _protocol())
    # a test scene of a validation town is not taken (only train scenes are)
    ds = _dataset({"train": ["Town01-lane00"], "test": ["Town05-lane00"]}, CARLA)
    with pytest.raises(UserError, match="meta.town"):
        scored_view(ds, "val", _protocol())


@pytest.mark.parametrize("split", ["train", "Val", "", "test "])
def test_only_test_and_val_are_scored(split):
    with pytest.raises(UserError, match="expected one of test, val"):
        check_split(split)
    with pytest.raises(UserError):
        scored_view(_dataset(CARLA_SPLITS, CARLA), split, _protocol())
    with pytest.raises(UserError):
        screening_split(split, "bench/x.py")
    assert check_split("test") == "test" and check_split("val") == "val"


def test_screening_refuses_test_in_one_line():
    assert screening_split("val", "bench/x.py") == "val"
    with pytest.raises(UserError) as e:
        screening_split("test", "bench/x.py")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("bench/x.py ") and "--split val" in msg and "validation split" in msg


def test_a_view_is_a_dataset_of_its_own():
    """The view replaces the splits only: the scenes and everything else are the dataset's."""
    ds = _dataset({"train": ["t"], "val": ["v"]})
    v = scored_view(ds, "val")
    same = {f.name for f in dataclasses.fields(Dataset)} - {"splits", "scored"}
    assert all(getattr(v, k) is getattr(ds, k) for k in same)
