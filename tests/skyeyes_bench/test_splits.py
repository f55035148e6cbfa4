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
from skyeyes_bench.splits import check_scorable, check_split, scored_view, screening_split


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


# --------------------------------------------------------------------------- data check and evaluate agree


@pytest.mark.parametrize("splits, says", [
    ({"train": ["a"]}, "field 'splits.test' is missing (splits: train)"),
    ({"train": ["a"], "test": []}, "field 'splits.test' is empty"),
])
def test_the_scored_split_must_hold_scenes(splits, says):
    ds = _dataset({**splits, "other": ["b"]})
    for call in (lambda: scored_view(ds, "test"), lambda: check_scorable(ds)):
        with pytest.raises(UserError) as e:
            call()
        msg = str(e.value)
        assert "\n" not in msg and msg.startswith(f"/data/ds/dataset.json: {says.replace('train', 'train, other')}"), msg
    # validation data of its own: its 'val' split is what it is scored on, and must hold scenes too
    with pytest.raises(UserError, match="field 'splits.val' is empty"):
        check_scorable(_dataset({"train": ["a"], "val": []}))
    assert check_scorable(_dataset({"train": ["a"], "val": ["b"]})) == "val"
    assert check_scorable(_dataset(CARLA_SPLITS, CARLA)) == "test"


@pytest.fixture
def evaltiny(tmp_path, monkeypatch):
    """(a tiny dataset of the test protocol, a complete submission of its test split made before any edit)."""
    from builders.evaluation import install_test_protocol, make_dataset
    from conftest import run_cli

    install_test_protocol(tmp_path, monkeypatch)
    root = make_dataset(tmp_path / "ds", scenes=2, seqs=1, frames=4)
    run_cli("submission", "template", "--data", str(root), "--out", str(tmp_path / "sub"), "--from-ground-truth")
    return root, tmp_path / "sub"


def _set_splits(root: Path, splits: dict) -> None:
    import json

    doc = json.loads((root / "dataset.json").read_text())
    doc["splits"] = splits
    (root / "dataset.json").write_text(json.dumps(doc))


_TEST = ["test-0-lane00", "test-0-lane01"]


@pytest.mark.parametrize("splits, says", [
    ({"train": ["train-0-lane00"]}, "field 'splits.test' is missing (splits: train)"),
    ({"train": ["train-0-lane00"], "eval": _TEST}, "field 'splits.test' is missing (splits: train, eval)"),
    ({"train": ["train-0-lane00"], "test": []}, "field 'splits.test' is empty"),
])
def test_data_check_refuses_what_evaluate_refuses_for_its_splits(evaltiny, splits, says):
    """A dataset without a test split to score: `data check` exits 2 with the one line `evaluate`
    gives for it (before, data check said OK and evaluate refused)."""
    from conftest import run_cli

    root, sub = evaltiny
    _set_splits(root, splits)
    rc, out, err = run_cli("data", "check", str(root), check=2)
    assert out == "" and err.count("\n") == 1 and err.startswith(f"skyeyes-bench: error: {root / 'dataset.json'}: {says}"), err
    rc, out, err_eval = run_cli("evaluate", str(sub), "--data", str(root), check=2)
    assert err_eval == err
    rc, out, err_tpl = run_cli("submission", "template", "--data", str(root), "--out", str(root.parent / "tpl"), check=2)
    assert err_tpl == err and not (root.parent / "tpl").exists()


@pytest.mark.parametrize("splits, split", [
    ({"train": ["train-0-lane00"], "test": _TEST}, "test"),
    ({"train": ["train-0-lane00"], "test": _TEST[:1], "val": _TEST[1:]}, "test"),
    ({"train": ["train-0-lane00"], "val": _TEST}, "val"),  # validation data of its own (SynthTown's <dataset>-val)
])
def test_what_data_check_passes_evaluate_accepts(evaltiny, splits, split):
    """The split `data check` says a dataset is scored on passes evaluate's own reading of it
    (`evaluate.open_inputs`: the dataset seen as the split the submission holds)."""
    from conftest import run_cli

    from skyeyes_bench.data.layout import open_dataset
    from skyeyes_bench.evaluate import open_inputs

    root, _ = evaltiny
    _set_splits(root, splits)
    run_cli("data", "check", str(root))
    assert check_scorable(open_dataset(root)) == split
    sub = root.parent / f"sub-{split}"
    run_cli("submission", "template", "--data", str(root), "--out", str(sub), "--split", split)
    manifest, proto, ds = open_inputs(sub, root)
    assert ds.scored == split and [s.name for s in ds.split("test")] == list(splits[split])
