"""SfM (reference/common/geometry/sfm.py) says why it gave no points, in its return value and in
the log: a pycolmap older than the API it calls, an exception inside pycolmap, no pycolmap."""

import logging
import sys
import types
from types import SimpleNamespace

import numpy as np
import pytest

from reference.common.geometry import sfm
from skyeyes_bench import imagefiles


def _frames(tmp_path, n=2):
    out = []
    for i in range(n):
        p = tmp_path / f"a{i}.png"
        imagefiles.write_image(p, np.full((8, 8, 3), 40 * i, np.uint8))
        out.append(SimpleNamespace(path=p, c2w=np.eye(4),
                                   intrinsics={"width": 8, "height": 8, "fx": 4.0, "fy": 4.0, "cx": 4.0, "cy": 4.0}))
    return out


def _fake_pycolmap(version, extract=None):
    """Just enough of pycolmap's surface for sfm_points to reach feature extraction."""
    m = types.ModuleType("pycolmap")
    m.__version__ = version
    m.logging = SimpleNamespace(minloglevel=0)
    m.ImageReaderOptions = lambda: SimpleNamespace()
    m.FeatureExtractionOptions = lambda: SimpleNamespace(sift=SimpleNamespace(), num_threads=0)
    m.CameraMode = SimpleNamespace(SINGLE=1)
    m.Device = SimpleNamespace(cpu=0)
    m.extract_features = extract or (lambda *a, **k: None)
    return m


def _run(monkeypatch, tmp_path, caplog, module):
    monkeypatch.setitem(sys.modules, "pycolmap", module)
    with caplog.at_level(logging.WARNING, logger=sfm.__name__):
        xyz, rgb, msg = sfm.sfm_points(_frames(tmp_path), tmp_path / "work")
    assert xyz.shape == (0, 3) and rgb.shape == (0, 3)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and msg in warnings[0], (msg, warnings)
    return msg


def test_sfm_exception_is_logged_with_its_reason(monkeypatch, tmp_path, caplog):
    def boom(*a, **k):
        raise RuntimeError("feature extraction exploded")

    msg = _run(monkeypatch, tmp_path, caplog, _fake_pycolmap("4.2.1", boom))
    assert msg == "SfM failed (RuntimeError: feature extraction exploded)"


def test_sfm_refuses_pycolmap_3_with_reason(monkeypatch, tmp_path, caplog):
    called = []
    msg = _run(monkeypatch, tmp_path, caplog, _fake_pycolmap("3.12.6", lambda *a, **k: called.append(1)))
    assert msg.startswith("pycolmap 3.12.6 is older than 4.0") and "pip install 'pycolmap>=4.0'" in msg
    assert called == []  # never reached the pipeline


def test_sfm_without_pycolmap_is_logged(monkeypatch, tmp_path, caplog):
    msg = _run(monkeypatch, tmp_path, caplog, None)  # sys.modules[name] = None makes the import fail
    assert msg.startswith("pycolmap unavailable")


def test_installed_pycolmap_has_the_api_sfm_calls():
    """The pin in pyproject (pycolmap>=4.0) is the API the code calls."""
    pycolmap = pytest.importorskip("pycolmap")
    assert sfm._major_version(pycolmap.__version__) >= sfm.PYCOLMAP_MIN_MAJOR
    for name in ("add_camera_with_trivial_rig", "add_image_with_trivial_frame"):
        assert hasattr(pycolmap.Reconstruction, name), name
    for name in ("extract_features", "match_exhaustive", "triangulate_points", "FeatureExtractionOptions"):
        assert hasattr(pycolmap, name), name
