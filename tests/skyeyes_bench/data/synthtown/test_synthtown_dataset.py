"""SynthTown datasets: layout validation, protocol structure, determinism, seeds, CLI, cache, gallery."""

import filecmp
import shutil

import numpy as np
import pytest
from conftest import run_cli

from skyeyes_bench import imagefiles, paths
from skyeyes_bench.cameras import Camera
from skyeyes_bench.data.layout import open_dataset
from skyeyes_bench.data.synthtown import PRESETS, ensure_dataset
from skyeyes_bench.data.synthtown import town as tw
from skyeyes_bench.data.synthtown.render import LABELS, Scene, render
from skyeyes_bench.errors import UserError
from skyeyes_bench.protocol import load_protocol


def test_smoke_dataset_opens_and_follows_the_protocol(synthtown_smoke):
    ds = open_dataset(synthtown_smoke)  # raises ValidationError on any problem
    proto = load_protocol("synthtown@1")
    assert ds.protocol == "synthtown@1" and ds.name == "synthtown-smoke"
    towns = {s: ds.scenes[s].meta["town"] for s in ds.scenes}
    assert {towns[s] for s in ds.splits["train"]} <= set(proto.data.train)
    assert {towns[s] for s in ds.splits["test"]} == set(proto.data.test)
    assert ds.meta["official"] is False and ds.meta["preset"] == "smoke" and ds.meta["seed"] == 0
    assert set(ds.meta["towns"]) == {"train-0", "test-0"}
    for name, scene in ds.scenes.items():
        assert name.startswith(scene.meta["town"] + "-lane")
        assert sorted(scene.sequences) == [f"yaw{45 * k:03d}" for k in range(8)]
        assert all(len(q) >= 16 for q in scene.sequences.values())  # FVD clips are 16 frames
        assert all(scene.layers().values())
        seq0 = scene.sequences["yaw000"]
        c = [f.camera() for f in seq0]
        # Every 2 m, 2 m high, pitch 0 (optical axis horizontal), yaw k*45 deg from the lane direction.
        steps = np.linalg.norm(np.diff([x.center for x in c], axis=0), axis=1)
        np.testing.assert_allclose(steps, proto.capture.ground_step_m, atol=1e-9)
        np.testing.assert_allclose([x.center[2] for x in c], proto.capture.ground_height_m)
        np.testing.assert_allclose([x.forward[2] for x in c], 0.0, atol=1e-12)
        fwd_lane = (c[1].center - c[0].center) / 2.0
        for k in range(8):
            f = scene.sequences[f"yaw{45 * k:03d}"].frames[0].camera().forward
            assert np.degrees(np.arccos(np.clip(f @ fwd_lane, -1, 1))) == pytest.approx(min(45 * k, 360 - 45 * k), abs=1e-6)
        for a in scene.aerial:
            ac = a.camera()
            assert ac.center[2] == pytest.approx(proto.capture.aerial_height_m)
            assert np.degrees(np.arcsin(ac.forward[2])) == pytest.approx(proto.capture.aerial_pitch_deg)
            # Over a ground point of the lane.
            assert min(np.linalg.norm(ac.center[:2] - x.center[:2]) for x in c) < 1e-9
        f = seq0.frames[3]
        depth, sem = f.depth(), f.semantics()
        assert depth.dtype == np.float32 and not np.isnan(depth).any()
        assert sem.max() < len(LABELS)
        np.testing.assert_array_equal(np.isinf(depth), sem == 0)


def test_same_seed_byte_identical_via_cli(synthtown_smoke, tmp_path):
    out = tmp_path / "again"
    rc, stdout, _ = run_cli("data", "synthtown", "--preset", "smoke", "--out", str(out), "--quiet")
    assert "wrote" in stdout
    cmp = filecmp.dircmp(synthtown_smoke, out)

    def same(c):
        assert not c.left_only and not c.right_only and not c.funny_files
        _, mismatch, errors = filecmp.cmpfiles(c.left, c.right, c.common_files, shallow=False)
        assert not mismatch and not errors, mismatch[:5]
        for sub in c.subdirs.values():
            same(sub)

    same(cmp)
    # Refuses to overwrite without --force: one-line error, exit 2.
    rc, _, err = run_cli("data", "synthtown", "--preset", "smoke", "--out", str(out), check=2)
    assert "already exists" in err and err.count("\n") == 1


def test_other_seed_gives_another_town():
    a, b = tw.make_town("test-0", 0, (3, 3)), tw.make_town("test-0", 1, (3, 3))
    assert not np.array_equal(a.xs, b.xs) or a.box_lo.shape != b.box_lo.shape
    again = tw.make_town("test-0", 0, (3, 3))
    np.testing.assert_array_equal(a.box_lo, again.box_lo)
    # Train and test towns of one seed differ too (the test town is held out).
    c = tw.make_town("train-0", 0, (3, 3))
    assert a.box_lo.shape != c.box_lo.shape or not np.array_equal(a.box_lo, c.box_lo)
    cam = Camera.from_ypr([a.xs[1] + 1.75, 0.0, 2.0], 90.0, 0.0, fov_deg=90, width=32, height=32)
    cam_b = Camera(cam.K, cam.c2w.copy(), 32, 32)
    cam_b.c2w[0, 3] = b.xs[1] + 1.75
    ia = render(Scene.from_town(a), cam, aa=1)[0]
    ib = render(Scene.from_town(b), cam_b, aa=1)[0]
    assert np.abs(ia - ib).mean() > 0.01


def test_ensure_dataset_uses_the_cache_copy(synthtown_smoke):
    target = paths.data_dir() / "synthtown-smoke"
    shutil.copytree(synthtown_smoke, target)
    before = (target / "dataset.json").stat().st_mtime_ns
    assert ensure_dataset("smoke", progress=False) == target
    assert (target / "dataset.json").stat().st_mtime_ns == before
    rc, stdout, _ = run_cli("data", "synthtown", "--preset", "smoke")
    assert stdout.startswith("exists")
    # A non-dataset folder under the cache name is refused, not overwritten.
    (paths.data_dir() / "synthtown-smoke-seed3").mkdir(parents=True)
    rc, _, err = run_cli("data", "synthtown", "--preset", "smoke", "--seed", "3", check=2)
    assert "no dataset.json" in err


def test_gallery_from_dataset(synthtown_smoke, tmp_path):
    out = tmp_path / "gallery.png"
    run_cli("data", "gallery", "--dataset", str(synthtown_smoke), "--out", str(out), "--rows", "2")
    w, h, c, _ = imagefiles.image_header(out)
    assert w > 6 * 48 and h > 2 * 48 and c in (3, 4)


def test_presets_are_consistent():
    """Every preset's data fits its own protocol; each protocol version has exactly one official
    preset, at the protocol's resolution; v2's official data has >= 8 test scenes and >= 2 FVD
    clips per sequence."""
    from skyeyes_bench.data.synthtown.generate import dataset_name

    official = {}
    for p in PRESETS.values():
        proto = load_protocol(p.protocol)
        assert p.frames >= 16
        assert {t for t, _ in p.lanes} == set(proto.data.train) | set(proto.data.test) or p.name == "smoke"
        assert p.fov_deg == proto.data.fov_deg
        if p.official:
            assert p.protocol not in official, f"two official presets for {p.protocol}"
            official[p.protocol] = p
            assert (p.width, p.height) == (proto.data.width, proto.data.height)
            assert proto.data.default_location == f"cache:{dataset_name(p.name, 0)}"
    assert set(official) == {"synthtown@1", "synthtown@2"}
    v2, proto2 = official["synthtown@2"], load_protocol("synthtown@2")
    assert sum(n for t, n in v2.lanes if t in proto2.data.test) >= 8
    fvd = proto2.metric("fvd")
    assert (v2.frames - fvd.clip_length) // fvd.clip_stride + 1 >= 2
    assert PRESETS["paper"].width == 512
    assert len({p.dataset for p in PRESETS.values()}) == len(PRESETS)  # one cache folder each


def test_cached_dataset_of_another_protocol_is_refused(tmp_path, monkeypatch):
    """An older release's data under the same cache name is an error, not silently scored."""
    import json

    from skyeyes_bench.data.synthtown.generate import dataset_name, ensure_dataset

    monkeypatch.setenv("SKYEYES_CACHE", str(tmp_path))
    folder = tmp_path / "data" / dataset_name("small", 0)
    folder.mkdir(parents=True)
    (folder / "dataset.json").write_text(json.dumps({"name": "synthtown-v2-small", "protocol": "synthtown@1",
                                                      "splits": {}, "scenes": [], "meta": {}}))
    with pytest.raises(UserError, match="made for protocol 'synthtown@1'.*remove the folder"):
        ensure_dataset("small")
    cfg = dict(PRESETS["small"].to_dict(), frames=20)
    (folder / "dataset.json").write_text(json.dumps({"name": "synthtown-v2-small", "protocol": "synthtown@2",
                                                      "splits": {}, "scenes": [], "meta": {"preset_config": cfg}}))
    with pytest.raises(UserError, match="another configuration than preset 'small'"):
        ensure_dataset("small")


def test_failed_run_leaves_nothing(tmp_path, monkeypatch):
    """A run that dies half-way leaves neither the dataset folder nor its temporary folder."""
    from skyeyes_bench.data.synthtown import generate

    calls = {"n": 0}
    real = generate._render_job

    def dying(job):
        calls["n"] += 1
        if calls["n"] > 3:
            raise KeyboardInterrupt
        return real(job)

    monkeypatch.setattr(generate, "_render_job", dying)
    with pytest.raises(KeyboardInterrupt):
        generate.generate_dataset(tmp_path / "ds", "smoke", progress=False, workers=1)
    assert list(tmp_path.iterdir()) == []


def test_ensure_dataset_waits_for_a_concurrent_run(monkeypatch):
    """Two threads asking for the same cache dataset: one renders, the other waits and reuses it."""
    import threading

    from skyeyes_bench.data.synthtown import generate

    calls = []
    real = generate.generate_dataset

    def counted(*a, **k):
        calls.append(a)
        return real(*a, **k)

    monkeypatch.setattr(generate, "generate_dataset", counted)
    results = []
    threads = [threading.Thread(target=lambda: results.append(generate.ensure_dataset("smoke", progress=False)))
               for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1 and len(results) == 2 and results[0] == results[1]
    assert open_dataset(results[0]).name == "synthtown-smoke"
