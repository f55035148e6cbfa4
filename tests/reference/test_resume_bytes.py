"""Issue 14: a killed `reproduce` resumes and reaches the same bytes as an uninterrupted run.

For each reference method (tiny settings) on the SynthTown smoke dataset: run A uninterrupted;
run B killed at stage boundaries (after the train-split fit, during a scene fit, after a scene
fit, mid-render), each time resumed into the same --out; then every submission file (frames as
bytes; submission.json without its timing, memory and creation fields) and every metric value in
results.json must equal A's. The kills are in-process (an exception no method catches, raised
from a wrapped method hook), since a real SIGKILL is hard to time; a kill during an atomic
checkpoint write is simulated by the temporary file such a kill leaves behind.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
from pathlib import Path

import pytest

from reference.methods import get_method_class
from reference.reproduce import run


class Killed(BaseException):
    """Stands in for SIGKILL: derives from BaseException so no `except Exception` swallows it."""


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest: a second thread only spins here


#: Tiny settings per method: each run takes seconds.
G3D = ["iterations=4", "init=plane", "train_lanes=0", "fallback_per_view=80", "densify_from=2", "densify_every=2",
       "densify_until=4"]
SETS = {
    "mean-frame": [],
    "mvs": ["planes=8", "num_sources=2", "threads=1"],
    "gaussians3d": G3D,
    "sugar": G3D,
}
#: Skyeyes and its variants: a few steps per stage, checkpoints every 2 steps, the `mvs` prior
#: (its smoke preset: seconds per lane) instead of SuGaR so the prior stage stays fast too.
DIFF = ["base_steps=4", "base_batch=2", "acm_steps=4", "acm_batch=2", "vcm_steps=4", "vcm_batch=1",
        "clip_frames=4", "sample_steps=2", "ckpt_every=2", "figure_frames=2", "prior_method=mvs", "threads=1"]
for _m in ("skyeyes", "skyeyes-no-vcm", "controlnet"):
    SETS[_m] = DIFF

#: submission.json fields that legitimately differ between two runs of the same computation.
VOLATILE = {"created", "timings", "peak_memory_mb"}


def submission_digest(out: Path) -> dict[str, str]:
    """sha256 of every file under submission/ (submission.json without its VOLATILE fields)."""
    sub = out / "submission"
    got = {}
    for p in sorted(sub.rglob("*")):
        if p.is_dir():
            continue
        rel = p.relative_to(sub).as_posix()
        if rel == "submission.json":
            doc = {k: v for k, v in json.loads(p.read_text()).items() if k not in VOLATILE}
            got[rel] = hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()
        else:
            got[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return got


def metric_values(out: Path) -> dict:
    """What results.json says about the frames: summary metrics, per-sequence and per-frame values."""
    res = json.loads((out / "results.json").read_text())
    # An unavailable metric's reason names the weights path, i.e. the run's cache: left out.
    metrics = {k: v for k, v in res["metrics"].items() if v["status"] != "unavailable"}
    assert "psnr" in metrics
    return {"metrics": metrics, **{k: res[k] for k in ("sequences", "frames", "sha256")}}


def reproduce(method: str, data: Path, out: Path, cache: Path, monkeypatch, jobs: int = 1) -> dict:
    """One smoke run. jobs=1 by default: the kills below patch the method in this process, which
    worker processes (`reference.parallel`) would not see."""
    monkeypatch.setenv("SKYEYES_CACHE", str(cache))  # the diffusion stages and priors cache there
    return run(method, "smoke", data=data, out=out, overrides=SETS[method], progress=False, jobs=jobs)


@contextlib.contextmanager
def kill_after(monkeypatch, owner, name: str, n: int = 1):
    """Raise Killed once `owner.<name>` (a method or module function) has returned `n` times,
    or, for `render_sequence`, once it has yielded `n` frames in all (frame n+1 is never handed
    over, so n frames reach the disk). The block must end in that kill."""
    orig = getattr(owner, name)
    state = {"n": 0, "killed": False}

    def kill(what):
        state["killed"] = True
        raise Killed(f"{name}: {what}")

    if name == "render_sequence":
        def wrapped(*a, **kw):
            for item in orig(*a, **kw):
                if state["n"] >= n:
                    kill(f"after {n} frames")
                state["n"] += 1
                yield item
    else:
        def wrapped(*a, **kw):
            res = orig(*a, **kw)
            state["n"] += 1
            if state["n"] >= n:
                kill(f"call {n} returned")
            return res

    with monkeypatch.context() as mp:
        mp.setattr(owner, name, wrapped)
        with pytest.raises(Killed):
            yield state
    assert state["killed"]


def leave_half_written(final: Path, source: Path) -> Path:
    """The temporary file a kill during `outputfiles.atomic_path(final)` leaves: half of `source`."""
    tmp = final.with_name(f".{final.stem}.k1ll3d.tmp{final.suffix}")
    data = source.read_bytes()
    tmp.parent.mkdir(parents=True, exist_ok=True)
    tmp.write_bytes(data[: len(data) // 2])
    return tmp


def assert_same_run(a: Path, b: Path) -> None:
    da, db = submission_digest(a), submission_digest(b)
    assert da.keys() == db.keys()
    differ = sorted(k for k in da if da[k] != db[k])
    assert not differ, f"{len(differ)} of {len(da)} submission files differ after resume, e.g. {differ[:3]}"
    assert metric_values(a) == metric_values(b)


def test_mean_frame_resumes_to_the_same_bytes(synthtown_smoke, tmp_path, monkeypatch):
    cls = get_method_class("mean-frame")
    a, b = tmp_path / "a", tmp_path / "b"
    reproduce("mean-frame", synthtown_smoke, a, tmp_path / "cache-a", monkeypatch)
    with kill_after(monkeypatch, cls, "fit_train"):
        reproduce("mean-frame", synthtown_smoke, b, tmp_path / "cache-b", monkeypatch)
    with kill_after(monkeypatch, cls, "render_sequence", 21):  # mid second sequence (16 frames each)
        reproduce("mean-frame", synthtown_smoke, b, tmp_path / "cache-b", monkeypatch)
    reproduce("mean-frame", synthtown_smoke, b, tmp_path / "cache-b", monkeypatch)
    assert_same_run(a, b)


@pytest.mark.parametrize("method", ["mvs", "gaussians3d", "sugar"])
def test_scene_fitting_methods_resume_to_the_same_bytes(method, synthtown_smoke, tmp_path, monkeypatch):
    cls = get_method_class(method)
    a, b = tmp_path / "a", tmp_path / "b"
    reproduce(method, synthtown_smoke, a, tmp_path / "cache-a", monkeypatch)
    # 1. Killed once the train split is learned (mvs: the appearance, saved as JSON).
    with kill_after(monkeypatch, cls, "fit_train"):
        reproduce(method, synthtown_smoke, b, tmp_path / "cache-b", monkeypatch)
    # 2. Killed while writing the scene's checkpoint: its temporary file is left, no checkpoint.
    with kill_after(monkeypatch, cls, "fit_one_scene"):
        reproduce(method, synthtown_smoke, b, tmp_path / "cache-b", monkeypatch)
    # The test lane's checkpoint (train lanes' MVS clouds are checkpoints of the appearance too).
    (ckpt,) = [p for p in (b / "work").rglob("*") if p.name in ("model.pt", "cloud.npz") and p.parent.name.startswith("test-")]
    tmp = leave_half_written(ckpt, ckpt)
    ckpt.unlink()
    (ckpt.parent / "fit.json").unlink()
    # 3. The resume ignores the half file and refits; killed mid second sequence (16 frames each).
    with kill_after(monkeypatch, cls, "render_sequence", 21):
        reproduce(method, synthtown_smoke, b, tmp_path / "cache-b", monkeypatch)
    assert ckpt.is_file() and tmp.is_file()
    # 4. The last resume renders from the checkpoint read back (run A from the model in memory).
    reproduce(method, synthtown_smoke, b, tmp_path / "cache-b", monkeypatch)
    assert_same_run(a, b)


def _diffusion_resume(method, data, tmp_path, monkeypatch):
    """Run A; run B killed in the prior stage (Skyeyes), mid-stage in the ACM training (a
    half-written checkpoint left beside the last good one) and mid-render; compare."""
    import diffusers  # noqa: F401  (a hard dependency of reference: a broken install fails here, never skips)
    from reference.common.diffusion import train
    from reference.common.mvs_cloud import MVSCloud

    cls = get_method_class(method)
    a, b = tmp_path / "a", tmp_path / "b"
    # Separate caches: the diffusion stages and prior renders live in the cache, not in --out.
    reproduce(method, data, a, tmp_path / "cache-a", monkeypatch)
    if cls.presets["smoke"].condition == "prior":
        # 1. Killed once the prior's appearance (the fused MVS cloud, the part `MVSCloud`) has
        # fitted the train lane, before its renders are cached.
        with kill_after(monkeypatch, MVSCloud, "fit_one_scene"):
            reproduce(method, data, b, tmp_path / "cache-b", monkeypatch)
    # 2. Killed in the ACM stage, after its first save (its step 2); a base stage (a ControlNet
    # branch from scratch; the smoke presets' concat UNet has none) saves at its steps 2 and 4 first.
    base_saves = 2 if cls.presets["smoke"].core.conditioning == "controlnet" else 0
    with kill_after(monkeypatch, train, "save_checkpoint", base_saves + 1):
        reproduce(method, data, b, tmp_path / "cache-b", monkeypatch)
    (acm,) = (tmp_path / "cache-b" / "reference" / "diffusion").glob("acm-*/train-4.pt")
    assert int(train.load_checkpoint(acm)["step"]) == 2
    leave_half_written(acm, acm)
    # 3. Killed mid second sequence.
    with kill_after(monkeypatch, cls, "render_sequence", 21):
        reproduce(method, data, b, tmp_path / "cache-b", monkeypatch)
    # 4. Done.
    reproduce(method, data, b, tmp_path / "cache-b", monkeypatch)
    assert_same_run(a, b)
    assert (a / "figure.png").read_bytes() == (b / "figure.png").read_bytes()


def test_controlnet_resumes_to_the_same_bytes(synthtown_smoke, tmp_path, monkeypatch):
    _diffusion_resume("controlnet", synthtown_smoke, tmp_path, monkeypatch)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["skyeyes", "skyeyes-no-vcm"])
def test_skyeyes_resumes_to_the_same_bytes(method, synthtown_smoke, tmp_path, monkeypatch):
    _diffusion_resume(method, synthtown_smoke, tmp_path, monkeypatch)
