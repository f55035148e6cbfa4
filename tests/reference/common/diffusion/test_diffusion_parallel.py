"""Data-parallel training under Hugging Face accelerate (issue 13): two CPU processes (gloo),
each on half of a global batch, end with the weights one process reaches on the whole batch."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import accelerate  # noqa: F401  (a hard dependency of reference: a broken install fails here, never skips)

sys.path.insert(0, str(Path(__file__).parent))
import _ddp_runner  # noqa: E402
from conftest import ROOT  # noqa: E402

RUNNER = Path(__file__).resolve().parent / "_ddp_runner.py"


def _launch(tmp: Path, batch: int) -> dict:
    out = tmp / "weights.pt"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    # `--multi_gpu` is accelerate's torch.distributed launcher; on a machine without GPUs the
    # processes run on the CPU with the gloo backend (MULTI_CPU).
    cmd = [sys.executable, "-m", "accelerate.commands.launch", "--multi_gpu", "--num_processes", "2",
           "--num_machines", "1", "--mixed_precision", "no", "--dynamo_backend", "no",
           "--main_process_port", "29517", str(RUNNER), str(out), str(batch),
           str(tmp / "ckpt")]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    return torch.load(out, weights_only=True)


def _max_diff(a: dict, b: dict) -> float:
    return max(float((a[k].float() - b[k].float()).abs().max()) for k in a)


def test_two_processes_equal_one_at_the_summed_batch(tmp_path):
    two = _launch(tmp_path / "two", batch=4)  # each process: 2 rows of the global 4
    assert two["processes"] == 2
    one_path = tmp_path / "one.pt"
    _ddp_runner.run(one_path, 4, tmp_path / "one")
    one = torch.load(one_path, weights_only=True)
    assert one["processes"] == 1
    init = _ddp_runner.core.build_model(_ddp_runner.CFG, control=True, seed=0).state_dict()
    moved = _max_diff(one["model"], init)  # how far 3 AdamW steps moved the weights (~3 lr)
    assert moved > 1e-2
    # Gradients are averaged by an all-reduce (sum, then / 2): float rounding only, which AdamW
    # turns into at most a few 1e-4 (its first steps move each weight by ~lr sign(grad)).
    assert _max_diff(two["model"], one["model"]) < 0.03 * moved
    assert two["losses"] == pytest.approx(one["losses"], rel=1e-5)
    # and the comparison can fail: one process at the per-process batch (2) ends elsewhere
    half_path = tmp_path / "half.pt"
    _ddp_runner.run(half_path, 2, tmp_path / "half")
    half = torch.load(half_path, weights_only=True)
    assert _max_diff(half["model"], one["model"]) > 0.3 * moved
