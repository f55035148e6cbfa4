"""Issue 37: adding a baseline is one new file in `reference/methods/` plus one registry line.

The toy below is such a file. The test puts it into the `reference.methods` package from a
temporary folder (so it is hashed into the run's cache key as a real method file is), adds its
registry line, and runs `reproduce` on it as a user would: nothing else in the checkout is
touched, and the submission holds what the toy says it renders, checked against a brute-force
choice of the nearest aerial view made here.
"""

import json

import cv2
import numpy as np
import pytest

from conftest import run_cli

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TOY = '''"""toy-nearest: every ground frame is the aerial view whose camera is nearest, resized."""

from dataclasses import dataclass

import cv2

from reference.common.priors import nearest_aerial
from reference.method import Method


@dataclass(frozen=True)
class ToyConfig:
    """Attributes: interpolation: OpenCV's resize filter ("area" or "linear")."""

    interpolation: str = "area"


class NearestAerial(Method):
    name = "toy-nearest"
    version = "0.1"
    presets = {"smoke": ToyConfig(), "small": ToyConfig(), "paper": ToyConfig()}

    def fit_scene_model(self, scene, *, progress):
        """Nothing to fit: the aerial views are the answer."""
        return None, {}

    def render_sequence(self, scene, sequence):
        flag = {"area": cv2.INTER_AREA, "linear": cv2.INTER_LINEAR}[self.config.interpolation]
        for f in sequence:
            yield cv2.resize(nearest_aerial(scene, f).image(), (f.width, f.height), interpolation=flag)
'''


def test_a_new_method_is_one_file_and_one_registry_line(synthtown_smoke, tmp_path, monkeypatch):
    import reference.methods
    from skyeyes_bench.data.layout import open_dataset
    from skyeyes_bench.imagefiles import read_image

    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "toy_nearest.py").write_text(TOY)
    monkeypatch.setattr(reference.methods, "__path__", [*reference.methods.__path__, str(pkg)])
    monkeypatch.setitem(reference.methods.METHODS, "toy-nearest", "reference.methods.toy_nearest:NearestAerial")

    out = tmp_path / "run"
    run_cli("reproduce", "--method", "toy-nearest", "--data", str(synthtown_smoke), "--out", str(out), "--quiet",
            "--set", "interpolation=linear")
    config = json.loads((out / "config.json").read_text())
    assert config["method"] == "toy-nearest" and config["config"]["interpolation"] == "linear"
    results = json.loads((out / "results.json").read_text())
    assert results["submission"]["method"] == "toy-nearest"
    assert results["metrics"]["psnr"]["status"] == "ok"

    ds = open_dataset(synthtown_smoke)
    checked = 0
    for scene in ds.split("test"):
        centres = np.array([a.c2w[:3, 3] for a in scene.aerial])
        for f in scene.ground:
            d2 = ((centres - f.c2w[:3, 3]) ** 2).sum(axis=1)  # brute force over every aerial view
            want = cv2.resize(scene.aerial[int(d2.argmin())].image(), (f.width, f.height),
                              interpolation=cv2.INTER_LINEAR)
            got = read_image(out / "submission" / scene.name / f.file)
            assert np.abs(got - want).max() <= 0.5 / 255 + 1e-6, f"{scene.name}/{f.file}"
            checked += 1
    assert checked == sum(len(s.ground) for s in ds.split("test")) > 0
