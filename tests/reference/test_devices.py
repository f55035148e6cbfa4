"""Devices resolved in one place (issue 34): `--device` errors before any work, "auto", the GPU
defaults of the diffusion presets and of scene-parallel lanes, decided without a GPU (what
torch reports about CUDA is monkeypatched; nothing here touches a GPU)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from conftest import run_cli
from reference.common.diffusion.presets import GPU_TRAINING
from reference.methods.skyeyes import PRESETS, Skyeyes
from reference.methods.sugar import SuGaR
from reference.parallel import GPU_LANES, available_cores, default_jobs
from skyeyes_bench.devices import device_name, resolve_device
from skyeyes_bench.errors import UserError


@pytest.fixture
def one_gpu(monkeypatch):
    """torch reports one CUDA device (no kernel is ever launched by these tests)."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without CUDA")
@pytest.mark.parametrize("name,match", [
    ("cuda", r"--device cuda: CUDA is not available on this machine \(.*\); use --device cpu"),
    ("cuda:1", r"--device cuda:1: CUDA is not available"),
    ("gpu0", r"--device 'gpu0': not a torch device \(expected auto, cpu, cuda or cuda:N\)"),
    ("xla", r"--device 'xla': unsupported device type"),
])
def test_a_device_this_machine_lacks_is_one_line(name, match):
    with pytest.raises(UserError, match=match) as e:
        resolve_device(name)
    assert "\n" not in str(e.value)


def test_auto_is_cuda_where_visible(monkeypatch, one_gpu):
    assert device_name("auto") == device_name(None) == "cuda"
    assert device_name("cuda:0") == "cuda:0"
    with pytest.raises(UserError, match=r"has 1 CUDA device\(s\) \(cuda:0 \.\. cuda:0\)"):
        resolve_device("cuda:1")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert device_name("auto") == "cpu"


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without CUDA")
@pytest.mark.parametrize("command", [
    ["reproduce", "--method", "skyeyes", "--device", "cuda"],
    ["reproduce", "--method", "sugar", "--device", "cuda"],
    ["reproduce", "--method", "mean-frame", "--device", "cuda:0"],
])
def test_reproduce_device_cuda_without_cuda_exits_2_in_one_line_before_any_work(command, tmp_path):
    rc, out, err = run_cli(*command, "--out", str(tmp_path / "o"), check=None)
    assert rc == 2, err
    assert len(err.strip().splitlines()) == 1 and "CUDA is not available" in err and "--device" in err
    assert not (tmp_path / "o").exists()  # refused before the output folder or any data


def test_gpu_training_shape_applies_on_cuda_only_and_yields_to_set(one_gpu):
    cpu, cpu_applied = Skyeyes.configure("small", device="cpu")
    assert cpu == dataclasses.replace(PRESETS["small"], device="cpu") and cpu_applied == ["device=cpu"]
    gpu, applied = Skyeyes.configure("small", device="cuda")
    want = GPU_TRAINING["small"]
    assert {k: getattr(gpu, k) for k in want} == want
    # the same frames seen as the CPU preset's ACM, in fewer steps
    assert gpu.acm_steps * gpu.acm_batch == PRESETS["small"].acm_steps * PRESETS["small"].acm_batch
    assert gpu.vcm_steps * gpu.vcm_batch == PRESETS["small"].vcm_steps * PRESETS["small"].vcm_batch  # and clips
    assert applied == ["device=cuda", *(f"{k}={v}" for k, v in want.items())]
    # "auto" resolves to CUDA here, so the same shape; a --set field is the user's
    auto, _ = Skyeyes.configure("small", ["acm_steps=5000"])
    assert auto.acm_steps == 5000 and auto.acm_batch == want["acm_batch"]
    # presets without a GPU shape (the README's smoke) are unchanged on a GPU
    assert Skyeyes.configure("smoke", device="cuda")[0] == dataclasses.replace(PRESETS["smoke"], device="cuda")


def test_scene_fits_run_several_lanes_at_once_on_a_gpu(one_gpu, tmp_path):
    cpu = SuGaR.from_preset("smoke", tmp_path / "a", device="cpu")
    gpu = SuGaR.from_preset("smoke", tmp_path / "b", device="cuda")
    assert default_jobs(cpu) == available_cores()
    assert default_jobs(gpu) == min(available_cores(), GPU_LANES)


def test_exact_fp32_turns_tf32_off_on_cuda_only_and_restores_it():
    from skyeyes_bench.devices import exact_fp32

    conv, mm = torch.backends.cudnn.conv, torch.backends.cuda.matmul
    before = conv.fp32_precision, mm.fp32_precision
    with exact_fp32("cpu"):
        assert (conv.fp32_precision, mm.fp32_precision) == before
    with exact_fp32("cuda"):  # only flags are set: no kernel runs
        assert (conv.fp32_precision, mm.fp32_precision) == ("ieee", "ieee")
    assert (conv.fp32_precision, mm.fp32_precision) == before
