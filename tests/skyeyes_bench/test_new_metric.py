"""Issue 59: adding a frame metric touches at most its module, the registry and a protocol file.

The toy below is such a module: a mean absolute error after a gamma curve, with a setting key
(`gamma`) that no other metric has. The test writes it to a temporary folder, adds its one
registry line (`metricspec.register_metric`), writes a protocol that asks for it with its
setting, and scores a small submission with `skyeyes_bench.evaluate` as a user would: nothing
else in the checkout is touched. Each frame's value is checked against numpy on the PNG files
(read with PIL, not the evaluator's reader), and a key the metric does not declare is refused.
"""

import sys

import numpy as np
import pytest
from builders.evaluation import TEST_PROTOCOL, blurred_submission, install_test_protocol, make_dataset
from PIL import Image

import skyeyes_bench as sb
from skyeyes_bench.data.layout import open_dataset
from skyeyes_bench.errors import UserError
from skyeyes_bench.evaluate import read_results
from skyeyes_bench.metricspec import METRICS, MetricDef, Setting, register_metric
from skyeyes_bench.protocol import MetricSpec, load_protocol, load_protocol_file
from skyeyes_bench.submission import expected_frames

TOY = '''"""toy_mae: mean absolute difference of the frames after a gamma curve."""

import numpy as np


def mae(preds, gts, settings):
    """[B] mean |pred^gamma - gt^gamma| of preds, gts [B, H, W, 3] in [0, 1] (gamma: the
    protocol's `gamma`, 1 when unset)."""
    assert preds.shape == gts.shape and preds.ndim == 4 and preds.shape[-1] == 3, (preds.shape, gts.shape)
    g = 1.0 if settings.gamma is None else settings.gamma
    return np.abs(preds ** g - gts ** g).mean(axis=(1, 2, 3))
'''

#: The protocol: the test protocol's data, capture and statistics; PSNR and the toy metric.
PROTOCOL = (TEST_PROTOCOL[:TEST_PROTOCOL.index("[metrics.psnr]")].replace('id = "evaltest"', 'id = "toymae"')
            + '[metrics.psnr]\naggregate = "mean"\n\n[metrics.toy_mae]\naggregate = "mean"\ngamma = 2\n\n'
            + TEST_PROTOCOL[TEST_PROTOCOL.index("[statistics]"):])


@pytest.fixture
def toy(tmp_path, monkeypatch):
    """The toy module importable as `toy_mae`, and its registry line; both undone afterwards."""
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "toy_mae.py").write_text(TOY)
    monkeypatch.syspath_prepend(str(tmp_path / "pkg"))
    monkeypatch.delitem(sys.modules, "toy_mae", raising=False)
    register_metric(MetricDef("toy_mae", "frame", False, frozenset({"aggregate", "gamma"}), "MAE", 4,
                              per_frame="toy_mae:mae", settings=(Setting("gamma", float),)))
    yield
    del METRICS["toy_mae"]


def _pixels(path) -> np.ndarray:
    """float64 [H, W, 3] in [0, 1] of an 8-bit RGB PNG, by PIL."""
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float64) / 255.0


def test_a_new_frame_metric_is_its_module_a_registry_line_and_a_protocol(toy, tmp_path, monkeypatch):
    install_test_protocol(tmp_path, monkeypatch, PROTOCOL)
    monkeypatch.setenv("SKYEYES_CACHE", str(tmp_path / "cache"))
    root = make_dataset(tmp_path / "ds", protocol="toymae@1", name="toytiny", scenes=2, seqs=2, frames=4)
    ds = open_dataset(root)
    sub = blurred_submission(ds, tmp_path / "sub", sigma=1.2)

    res = sb.evaluate(sub, root, out=tmp_path / "toy.json")

    assert load_protocol("toymae@1").metric("toy_mae").gamma == 2.0  # a float setting: the int is converted
    assert list(res["metrics"]) == ["psnr", "toy_mae"]
    m = res["metrics"]["toy_mae"]
    assert m["status"] == "ok" and m["kind"] == "frame" and m["higher_is_better"] is False and m["n"] == 16
    gts = {(scene, f.file): _pixels(f.path) for scene, f in expected_frames(ds)}  # the ground truth
    assert sorted((r["scene"], r["file"]) for r in res["frames"]) == sorted(gts)
    plain = []
    for r in res["frames"]:
        pred, gt = _pixels(sub / r["scene"] / r["file"]), gts[(r["scene"], r["file"])]
        independent = np.mean(np.abs(pred ** 2 - gt ** 2))  # gamma = 2
        assert r["toy_mae"] == pytest.approx(independent, rel=1e-5, abs=1e-7), r["file"]
        plain.append(np.mean(np.abs(pred - gt)))  # the same without the setting (gamma 1)
    # ... differs from each value by far more than the tolerance above: the protocol's gamma reached the metric
    assert all(abs(r["toy_mae"] - p) > 1e-4 * p for r, p in zip(res["frames"], plain))
    assert min(r["toy_mae"] for r in res["frames"]) > 1e-4  # the blur shows: a value of 0 would test nothing
    assert m["value"] == pytest.approx(np.mean([r["toy_mae"] for r in res["frames"]]), rel=1e-12)
    # the results file holds it in every frame record and reads back (its checks know the metric)
    written, _ = read_results(tmp_path / "toy.json", features=False)
    assert [r["toy_mae"] for r in written["frames"]] == [r["toy_mae"] for r in res["frames"]]
    assert written["metrics"]["toy_mae"]["value"] == m["value"]


def test_a_key_the_new_metric_does_not_declare_is_refused(toy, tmp_path):
    bad = tmp_path / "toymae" / "v1.toml"
    bad.parent.mkdir()
    bad.write_text(PROTOCOL.replace("gamma = 2\n", "gamma = 2\nbeta = 1\n"))
    with pytest.raises(UserError) as e:
        load_protocol_file(bad)
    assert str(e.value) == f"{bad}: unknown key 'metrics.toy_mae.beta' (known: aggregate, gamma)"
    assert "\n" not in str(e.value)
    bad.write_text(PROTOCOL.replace("gamma = 2\n", 'gamma = "two"\n'))
    with pytest.raises(UserError, match=r"key 'metrics.toy_mae.gamma' must be float, got 'two'$"):
        load_protocol_file(bad)
    with pytest.raises(UserError, match="metric 'toy_mae': unknown setting 'beta'"):
        MetricSpec("toy_mae", gamma=2.0, beta=1)  # built in code: the same keys

def test_without_its_registry_line_the_metric_is_unknown(tmp_path):
    """The registry line is what makes the metric known: the same protocol without it is refused."""
    path = tmp_path / "toymae" / "v1.toml"
    path.parent.mkdir()
    path.write_text(PROTOCOL)
    with pytest.raises(UserError, match=r"unknown metric 'metrics.toy_mae' \(known: psnr, "):
        load_protocol_file(path)
