"""The method life cycle (`reference.method`): config from preset + overrides, the checkpoint and
resume rule, cached time; and the camera rays the methods now take from `Camera.rays`, checked
against the hand-built rays they replaced."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from reference.method import Method, cache_key, json_sha
from skyeyes_bench.cameras import Camera
from skyeyes_bench.errors import UserError


@dataclasses.dataclass(frozen=True)
class Inner:
    a: int = 1


@dataclasses.dataclass(frozen=True)
class Cfg:
    steps: int = 3
    scale: float = 1.0
    inner: Inner = Inner()
    device: str = "cpu"
    threads: int | None = None


class Toy(Method):
    """A scene's "model" is its name's length times `steps`; counts its fits."""

    name = "toy"
    presets = {"smoke": Cfg(), "big": Cfg(steps=30)}
    scene_checkpoint = "model.json"

    def __init__(self, config, workdir, **kw):
        super().__init__(config, workdir, **kw)
        self.fits = 0

    def fit_scene_model(self, scene, *, progress):
        self.fits += 1
        return np.full(3, len(scene.name) * self.config.steps, np.float32), {"note": "fitted"}

    def save_scene_model(self, model, path):
        path.write_text(json.dumps(model.tolist()))

    def load_scene_model(self, path):
        return np.asarray(json.loads(path.read_text()), np.float32)

    def render_sequence(self, scene, sequence):
        yield from ()


@dataclasses.dataclass
class FakeScene:
    name: str


def test_configure_applies_sets_then_values_device_and_records_the_sets(monkeypatch):
    import torch

    # torch reports two GPUs (nothing runs on them): configure checks the device exists
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    cfg, sets = Toy.configure("big", ["scale=0.5", "inner.a=4"], values={"steps": 7}, device="cuda:1")
    assert cfg == Cfg(steps=7, scale=0.5, inner=Inner(a=4), device="cuda:1")
    assert sets == ["scale=0.5", "inner.a=4", "device=cuda:1"]
    assert Toy.from_preset("big", Path("/tmp/unused-toy"), steps=7).config == Cfg(steps=7)
    with pytest.raises(UserError, match="unknown preset of method 'toy'"):
        Toy.configure("huge")
    with pytest.raises(UserError, match="takes no pretrained model"):
        Toy.configure("smoke", pretrained="/nowhere")

    class CpuOnly(Toy):
        presets = {"smoke": Inner()}

    assert CpuOnly.configure("smoke", device="cpu")[0] == Inner()
    with pytest.raises(UserError, match="runs on the CPU only"):
        CpuOnly.configure("smoke", device="cuda")


def test_cache_key_is_the_json_hash_it_always_was():
    import hashlib

    args = dict(method="toy", version="0.1", config={"t": (1, 2)}, seed=0, data_sha="d", code="c")
    blob = json.dumps({"method": "toy", "version": "0.1", "config": {"t": (1, 2)}, "seed": 0, "data": "d",
                       "code": "c"}, sort_keys=True)
    assert cache_key(**args) == hashlib.sha256(blob.encode()).hexdigest()[:16]
    assert json_sha({"b": 1, "a": Path("x")}) == hashlib.sha256(b'{"a": "x", "b": 1}').hexdigest()


def test_fit_scene_saves_then_resumes_at_its_recorded_cost(tmp_path):
    scene = FakeScene("lane7")
    a = Toy.from_preset("smoke", tmp_path)
    a.fit_scene(scene)
    folder = tmp_path / "scenes" / "lane7"
    assert {p.name for p in folder.iterdir()} == {"model.json", "fit.json"}  # no temporary file left
    stats = json.loads((folder / "fit.json").read_text())
    assert stats["note"] == "fitted" and stats["fit_seconds"] >= 0 and a.cached_s == 0
    # A new instance on the same workdir reads the checkpoint back instead of fitting, and counts
    # the fit's recorded seconds as work taken from a cache.
    stats["fit_seconds"] = 12.5
    (folder / "fit.json").write_text(json.dumps(stats))
    b = Toy.from_preset("smoke", tmp_path)
    b.fit_scene(scene)
    assert b.fits == 0 and b.cached_s == 12.5 and b.scene_stats["lane7"]["note"] == "fitted"
    np.testing.assert_array_equal(b.scene_model(scene), a.scene_model(scene))
    with pytest.raises(RuntimeError, match="before fit_scene"):
        b.scene_model(FakeScene("other"))


def test_a_failed_save_leaves_no_checkpoint_and_the_next_run_refits(tmp_path):
    scene = FakeScene("lane1")

    class Broken(Toy):
        def save_scene_model(self, model, path):
            path.write_text("[1, 2")  # half written, then killed
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        Broken.from_preset("smoke", tmp_path).fit_scene(scene)
    folder = tmp_path / "scenes" / "lane1"
    assert [p.name for p in folder.iterdir()] == ["fit.json"]  # stats first, checkpoint last
    m = Toy.from_preset("smoke", tmp_path)
    m.fit_scene(scene)
    assert m.fits == 1 and m.cached_s == 0


def test_one_hook_parts_fit_first_on_every_scene_and_no_checkpoint_refits(tmp_path):
    """`fit_scenes` fits the method's parts on all scenes at once, then `fit_scene_model` per
    scene; without a `scene_checkpoint` nothing is written and a new run fits again, in turn."""
    calls: list = []

    class Part:
        def fit_scenes(self, scenes, *, progress, jobs):
            calls.append(("part", [s.name for s in scenes], jobs))
            return 4.0  # seconds its caches saved

    class NoCheckpoint(Toy):
        scene_checkpoint = None

        def scene_parts(self):
            return [Part()]

        def fit_scene_model(self, scene, *, progress):
            calls.append(("scene", scene.name))
            return super().fit_scene_model(scene, progress=progress)

    scenes = [FakeScene("a"), FakeScene("bb")]
    m = NoCheckpoint.from_preset("smoke", tmp_path, threads=1)
    m.jobs = 2
    assert not m.parallel_scenes  # nothing to hand back from a worker: fitted in this process
    m.fit_scenes(scenes)
    assert calls == [("part", ["a", "bb"], 2), ("scene", "a"), ("scene", "bb")]
    assert m.cached_s == 4.0 and m.scene_stats["bb"] == {"note": "fitted"}
    np.testing.assert_array_equal(m.scene_model(scenes[1]), [6, 6, 6])  # len("bb") * steps 3
    assert not (tmp_path / "scenes").exists()
    again = NoCheckpoint.from_preset("smoke", tmp_path)
    again.fit_scene(scenes[0])
    assert again.fits == 1 and calls[-2:] == [("part", ["a"], 1), ("scene", "a")]
    # with a checkpoint and one thread a method's scenes may go to worker processes; not on more
    assert Toy.from_preset("smoke", tmp_path, threads=1).parallel_scenes
    assert not Toy.from_preset("smoke", tmp_path, threads=2).parallel_scenes


def test_device_auto_resolves_and_threads_follow_the_config(monkeypatch, tmp_path):
    import torch

    m = Toy(Cfg(device="auto", threads=1), tmp_path)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert m.device == "cpu"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert m.device == "cuda"
    n = torch.get_num_threads()
    try:
        m.use_threads()
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(n)


# --------------------------------------------------------------------------- rays


class FakeFrame:
    def __init__(self, cam: Camera, seed: int):
        self.cam, self.width, self.height = cam, cam.width, cam.height
        self.img = np.random.default_rng(seed).random((cam.height, cam.width, 3)).astype(np.float32)

    def camera(self):
        return self.cam

    def image(self):
        return self.img


def _frames() -> list[FakeFrame]:
    """Aerial-like and level cameras, off-centre principal points: some rows above the horizon."""
    out = []
    for i, (pitch, yaw) in enumerate([(-45, 0), (-10, 30), (0, 200), (5, -60), (-90, 10)]):
        cam = Camera.from_ypr([3.0 * i, -2.0, 50.0], yaw, pitch, 3.0, fov_deg=70, width=24, height=18)
        K = cam.K.copy()
        K[0, 2] += 1.3
        K[1, 2] -= 2.1
        out.append(FakeFrame(Camera(K, cam.c2w, cam.width, cam.height), i))
    return out


def _sky_colour_by_hand(frames):
    """The rays `sky_colour` built by hand before it used Camera.rays (the slow reference)."""
    acc, n = np.zeros(3), 0
    for f in frames:
        cam = f.camera()
        v = np.arange(f.height) + 0.5
        dz = (v - cam.K[1, 2]) / cam.K[1, 1] * cam.c2w[2, 1] + cam.c2w[2, 2]
        rows = dz > 0.05
        if rows.any():
            acc += f.image()[rows].reshape(-1, 3).sum(0)
            n += int(rows.sum()) * f.width
    return (acc / n).astype(np.float32) if n else np.full(3, 0.5, np.float32)


def test_sky_colour_takes_the_same_rows_as_the_hand_built_rays():
    from reference.common.appearance import sky_colour

    frames = _frames()
    for f in frames:  # the ray z through each row at the principal point's column
        cam = f.camera()
        v = np.arange(f.height) + 0.5
        _, d = cam.rays(np.stack([np.full_like(v, cam.K[0, 2]), v], 1), normalize=False)
        by_hand = (v - cam.K[1, 2]) / cam.K[1, 1] * cam.c2w[2, 1] + cam.c2w[2, 2]
        np.testing.assert_allclose(d[:, 2], by_hand, rtol=0, atol=1e-12)
    assert any((_sky_colour_by_hand([f]) != 0.5).any() for f in frames)  # some frame sees sky
    np.testing.assert_array_equal(sky_colour(frames), _sky_colour_by_hand(frames))
    np.testing.assert_array_equal(sky_colour(frames[-1:]), np.full(3, 0.5, np.float32))  # nadir: none


def test_ground_plane_points_rays_are_the_hand_built_ones_bit_for_bit():
    from reference.common.geometry.sfm import ground_plane_points

    frames = _frames()
    rng = np.random.default_rng(0)
    for f in frames:
        cam = f.camera()
        u, v = rng.uniform(0, cam.width, 50), rng.uniform(0, cam.height, 50)
        d_cam = np.stack([(u - cam.K[0, 2]) / cam.K[0, 0], (v - cam.K[1, 2]) / cam.K[1, 1], np.ones_like(u)], -1)
        _, d = cam.rays(np.stack([u, v], 1), normalize=False)
        np.testing.assert_array_equal(d, d_cam @ cam.c2w[:3, :3].T)
    xyz, rgb = ground_plane_points(frames, per_view=200, seed=3)
    assert len(xyz) > 0 and np.isfinite(xyz).all() and (xyz[:, 2] > -1e-6).all()
