"""`skyeyes-bench reproduce`: overrides, cache keys, an end-to-end smoke run and its resume."""

import json

import pytest
import torch

from conftest import run_cli
from reference.methods.gaussians3d import PRESETS
from reference.reproduce import cache_key, parse_overrides
from skyeyes_bench.errors import UserError


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)  # shared 2-core machine: a second OpenMP thread only spins
    yield
    torch.set_num_threads(n)


def test_overrides_are_typed_and_checked():
    cfg = PRESETS["smoke"]
    got = parse_overrides(cfg, ["iterations=12", "init=plane", "margin_m=7.5"])
    assert got == {"iterations": 12, "init": "plane", "margin_m": 7.5}
    assert isinstance(got["iterations"], int) and isinstance(got["margin_m"], float)
    with pytest.raises(UserError, match="not a field"):
        parse_overrides(cfg, ["nope=1"])
    with pytest.raises(UserError, match="expected a int"):
        parse_overrides(cfg, ["iterations=1.5"])
    with pytest.raises(UserError, match="KEY=VALUE"):
        parse_overrides(cfg, ["iterations"])


def test_bool_overrides_accept_the_usual_spellings_only():
    import dataclasses

    @dataclasses.dataclass
    class C:
        flag: bool = True

    for raw, want in [("false", False), ("0", False), ("No", False), ("true", True), ("1", True), ("YES", True)]:
        assert parse_overrides(C(), [f"flag={raw}"]) == {"flag": want}
    with pytest.raises(UserError, match="expected a bool"):
        parse_overrides(C(), ["flag=maybe"])


def test_cache_key_depends_on_every_input():
    base = dict(method="sugar", version="0.1", config={"a": 1}, seed=0, data_sha="d", code="c")
    k0 = cache_key(**base)
    assert k0 == cache_key(**base)
    for field, val in (("method", "gaussians3d"), ("version", "0.2"), ("config", {"a": 2}), ("seed", 1),
                       ("data_sha", "e"), ("code", "x")):
        assert cache_key(**{**base, field: val}) != k0, field


def test_unknown_method_and_preset_are_one_line_errors(tmp_path):
    rc, _, err = run_cli("reproduce", "--method", "nope", "--data", str(tmp_path), check=2)
    assert "unknown method 'nope'" in err and "sugar" in err
    rc, _, err = run_cli("reproduce", "--method", "sugar", "--preset", "huge", "--data", str(tmp_path), check=2)
    assert "unknown preset" in err


def test_end_to_end_smoke_and_resume(synthtown_smoke, tmp_path):
    out = tmp_path / "run"
    args = ["reproduce", "--method", "gaussians3d", "--preset", "smoke", "--data", str(synthtown_smoke),
            "--out", str(out), "--quiet", "--set", "iterations=6", "--set", "init=plane", "--set", "train_lanes=0",
            "--set", "fallback_per_view=80", "--set", "densify_from=2", "--set", "densify_every=2"]
    rc, stdout, _ = run_cli(*args)
    assert "psnr" in stdout
    res = json.loads((out / "results.json").read_text())
    assert res["metrics"]["psnr"]["status"] == "ok" and res["metrics"]["psnr"]["value"] > 5
    sub = json.loads((out / "submission" / "submission.json").read_text())
    n_frames = len(res["frames"])
    assert len(sub["timings"]["per_frame_render_s"]) == n_frames
    assert sub["timings"]["fit_s"] > 0 and sub["peak_memory_mb"] > 0
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["config"]["iterations"] == 6 and cfg["overrides"][0] == "iterations=6"
    (work,) = (out / "work").iterdir()
    ckpts = list(work.rglob("model.pt"))
    assert len(ckpts) == 1
    renders = sorted((work / "renders").rglob("*.png"))
    assert len(renders) == n_frames

    # Interrupted run: a frame and the outputs are missing. Resume refits nothing, re-renders
    # only the missing sequence's frames and rewrites submission + results.
    ck_mtime = ckpts[0].stat().st_mtime_ns
    other = renders[-1]
    other_mtime = other.stat().st_mtime_ns
    renders[0].unlink()
    (out / "results.json").unlink()
    run_cli(*args)
    assert ckpts[0].stat().st_mtime_ns == ck_mtime
    assert renders[0].is_file()
    assert json.loads((out / "results.json").read_text())["metrics"]["psnr"]["status"] == "ok"
    assert other.stat().st_mtime_ns == other_mtime  # complete sequences are not re-rendered
