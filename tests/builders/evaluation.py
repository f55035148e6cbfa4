"""Helpers shared by the evaluate/submission/leaderboard tests (no tests here): a test protocol that
uses the test-only `random-*` extractors, and (from `skyeyes_bench.synthetic`, which bench/ uses
too) a tiny dataset built with DatasetWriter, a blurred submission of it and the comparable part of
a results document."""

import contextlib
import shutil
from pathlib import Path

import numpy as np

from skyeyes_bench.synthetic import blurred_submission, make_dataset  # noqa: F401  (the tests import them from here)
from skyeyes_bench.synthetic import comparable as scores  # noqa: F401

ROOT = Path(__file__).resolve().parents[2]  # the repository

TEST_PROTOCOL = """
id = "evaltest"
version = 1
title = "evaluator tests"
description = "test-only protocol: random extractors, small statistics"
reference = "tests"

[data]
source = "synthtown"
train = ["train-0"]
test = ["test-0"]
width = 32
height = 32
fov_deg = 90.0

[capture]
ground_height_m = 2.0
ground_pitch_deg = 0.0
ground_step_m = 2.0
yaws_deg = [0.0, 90.0]
aerial_height_m = 52.0
aerial_pitch_deg = -45.0
sequence = "test"

[metrics.psnr]
aggregate = "mean"

[metrics.ssim]
aggregate = "mean"
window = 11
sigma = 1.5
k1 = 0.01
k2 = 0.03

[metrics.lpips]
aggregate = "mean"
extractor = "lpips-alex-v0.1"

[metrics.fid]
extractor = "random-image-64"
resize = "none"

[metrics.kid]
extractor = "random-image-64"
resize = "none"
subset_size = 100
num_subsets = 5

[metrics.fvd]
extractor = "random-video-64"
resize = "none"
clip_length = 4
clip_stride = 4

[metrics.kvd]
extractor = "random-video-64"
resize = "none"
clip_length = 4
clip_stride = 4
subset_size = 20
num_subsets = 5

[statistics]
bootstrap_resamples = 200
interval = 0.95
seed = 0
cluster = "sequence"
emcee_walkers = 16
emcee_steps = 600
emcee_burn = 100
"""


#: The test protocol resampling scenes (lanes) instead of sequences, as synthtown@2 does.
SCENE_PROTOCOL = TEST_PROTOCOL.replace('id = "evaltest"', 'id = "evalscene"').replace(
    'cluster = "sequence"', 'cluster = "scene"')


def install_test_protocol(tmp_path, monkeypatch, text: str = TEST_PROTOCOL) -> Path:
    """A copy of protocols/ plus protocols/<id>/v<version>.toml of `text` (default: evaltest/v1.toml);
    SKYEYES_PROTOCOLS points at it. Call again with another text to add a second protocol."""
    import tomllib

    root = tmp_path / "protocols"
    if not root.exists():
        shutil.copytree(ROOT / "protocols", root)
    raw = tomllib.loads(text)
    (root / raw["id"]).mkdir(exist_ok=True)
    (root / raw["id"] / f"v{raw['version']}.toml").write_text(text)
    monkeypatch.setenv("SKYEYES_PROTOCOLS", str(root))
    return root


@contextlib.contextmanager
def protocol_env(tmp: Path, text: str = TEST_PROTOCOL):
    """For module-scoped fixtures (the per-test cache and monkeypatch are not there yet): the
    protocol `text` installed under `tmp` and the cache at `tmp/cache`, both undone on exit.
    Yields the MonkeyPatch (to install more protocols or set more variables)."""
    import pytest

    mp = pytest.MonkeyPatch()
    try:
        install_test_protocol(tmp, mp, text)
        mp.setenv("SKYEYES_CACHE", str(tmp / "cache"))
        yield mp
    finally:
        mp.undo()


def indexed_submission(ds, out: Path, method="indexed", step=10) -> Path:
    """A submission whose frame of index i is the ground truth squeezed into a third of the range
    plus a brightness of 20 + step * i levels: a frame's mean brightness says which it is (frame
    order visible after lossy compression)."""
    from skyeyes_bench.submission import SubmissionWriter, expected_frames

    with SubmissionWriter(out, dataset=ds, method=method, method_version="1", config={"step": step}) as w:
        for scene, f in expected_frames(ds):
            w.add(scene, f, np.clip(f.image() / 3 + (20 + step * int(f.index)) / 255, 0, 1))
        w.finish(timings={"fit_s": 1.0, "render_s": 2.0, "per_frame_render_s": [0.01]}, peak_memory_mb=10.0)
    return out


def scipy_fid(x, y) -> float:
    """The Frechet distance of two feature sets [N, D] by scipy's sqrtm: the independent reference
    the evaluate tests hold FID and FVD to."""
    import scipy.linalg

    s1, s2 = np.cov(x, rowvar=False), np.cov(y, rowvar=False)
    return float(((x.mean(0) - y.mean(0)) ** 2).sum() + np.trace(s1) + np.trace(s2)
                 - 2 * np.trace(scipy.linalg.sqrtm(s1 @ s2).real))
