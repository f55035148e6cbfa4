"""Scene fits in worker processes (`reference.parallel`): the same clouds as fits in turn, each
fit's seconds counted once, the workers' log lines in the caller's log."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from conftest import run_cli
from reference.methods.mvs import MVS
from reference.parallel import most_workers
from skyeyes_bench.data.layout import open_dataset

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: Seconds per lane: few planes and sources, no train lanes.
TINY = {"planes": 8, "num_sources": 2, "train_lanes": 0}


def fit(data, workdir, jobs: int, **values) -> tuple[MVS, list]:
    ds = open_dataset(data)
    scenes = ds.split("train") + ds.split("test")  # smoke has one test lane: its train lanes too
    m = MVS.from_preset("smoke", workdir, progress=False, **{**TINY, **values})
    m.jobs = jobs
    m.fit_scenes(scenes)
    return m, scenes


def test_workers_fit_the_same_scenes_and_count_their_seconds_once(synthtown_smoke, tmp_path, caplog):
    in_turn, scenes = fit(synthtown_smoke, tmp_path / "in-turn", 1)
    assert len(scenes) >= 2
    with caplog.at_level(logging.INFO):
        workers, _ = fit(synthtown_smoke, tmp_path / "workers", 2)
    assert f"fitting {len(scenes)} scenes in 2 worker processes" in caplog.text
    assert most_workers() == 2  # the run's peak memory counts two workers side by side
    for s in scenes:  # each worker's own log line ("<scene>: N fused points") reached this log
        assert f"{s.name}: " in caplog.text and "fused points" in caplog.text
        a, b = in_turn.scene_model(s), workers.scene_model(s)
        assert len(a.xyz) > 0
        for field in ("xyz", "rgb", "normals", "footprint"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    # Fitted now, by workers: their time is in the caller's wall clock, not cached work.
    assert workers.cached_s == 0.0
    # Resumed by a later run: each fit's recorded seconds are its original cost.
    again, _ = fit(synthtown_smoke, tmp_path / "workers", 2)
    recorded = [json.loads((again.scene_dir(s) / "fit.json").read_text())["fit_seconds"] for s in scenes]
    assert min(recorded) > 0 and again.cached_s == pytest.approx(sum(recorded))


def test_multithreaded_methods_fit_in_turn(synthtown_smoke, tmp_path, caplog):
    """A method fitting on several threads would oversubscribe the cores: no workers."""
    with caplog.at_level(logging.INFO):
        m, scenes = fit(synthtown_smoke, tmp_path / "w", 2, threads=2)
    assert "worker processes" not in caplog.text
    assert all(len(m.scene_model(s).xyz) > 0 for s in scenes)


def test_jobs_below_one_is_refused(tmp_path):
    _, _, err = run_cli("reproduce", "--method", "mean-frame", "--jobs", "0", "--out", str(tmp_path / "o"), check=2)
    assert "--jobs 0" in err and ">= 1" in err
