"""Issue 35: one output discipline for every command (`outputfiles.check_output`, `reading`,
`output_lock`, `write_unit`).

- An output never is, holds or lies inside an input, with or without --force; --force replaces an
  earlier output of the same kind only (`outputfiles.OutputKind`).
- Results and their sidecar are one unit: two runs to one --out never mix them; a run killed at
  any point is repeated without --force and writes the same bytes.
- Created files and folders get the user's umask.
- No traceback or hang: a named pipe as protocol, a 5000-digit version, a full disk, a bad
  --aerial-radius, symlinks out of a capture or a dataset.

Every refusal exits 2 with one stderr line, writes nothing and destroys no input: each case
snapshots the whole world (paths, types, sha256 of files, symlink targets) before and after.
"""

import errno
import hashlib
import json
import os
import shutil
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
from builders.captures import make_carla, make_matrixcity
from builders.evaluation import TEST_PROTOCOL, make_dataset
from conftest import ROOT, run_cli

from skyeyes_bench import outputunit
from skyeyes_bench.evaluate import FEATURES_OUTPUT

NINES = "9" * 5000


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """Inputs for every command: protocols (with evaltest@1), a tiny dataset, a perfect submission
    (`submission template --from-ground-truth`), two shard partials, CARLA and MatrixCity captures,
    and a file and a folder that no command wrote."""
    base = tmp_path_factory.mktemp("outputs")
    shutil.copytree(ROOT / "protocols", base / "protocols")
    (base / "protocols" / "evaltest").mkdir()
    (base / "protocols" / "evaltest" / "v1.toml").write_text(TEST_PROTOCOL)
    w = base / "w"
    mp = pytest.MonkeyPatch()
    try:
        mp.setenv("SKYEYES_PROTOCOLS", str(base / "protocols"))
        mp.setenv("SKYEYES_CACHE", str(base / "cache"))
        make_dataset(w / "ds", scenes=2, seqs=1, frames=4)
        run_cli("submission", "template", "--data", str(w / "ds"), "--out", str(w / "sub"), "--from-ground-truth")
        for i in (0, 1):
            run_cli("evaluate", "--allow-missing", str(w / "sub"), "--data", str(w / "ds"), "--shard", f"{i}/2",
                    "--out", str(w / f"p{i}.json"), "--quiet")
        make_carla(w / "carla")
        make_matrixcity(w / "mc", depth=True)
    finally:
        mp.undo()
    (w / "notes.txt").write_text("not an output of skyeyes-bench\n")
    (w / "home").mkdir()
    (w / "home" / "thesis.tex").write_text("years of work\n")
    (w / "outside.png").write_bytes((w / "carla" / "rgb" / "000000.png").read_bytes())
    return base


@pytest.fixture
def w(world, monkeypatch):
    monkeypatch.setenv("SKYEYES_PROTOCOLS", str(world / "protocols"))
    return world / "w"


def snapshot(root: Path) -> dict[str, str]:
    """Every path under root: a file's sha256, a symlink's target, a folder, or another kind."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            rel = str(p.relative_to(root))
            if p.is_symlink():
                out[rel] = "-> " + os.readlink(p)
            elif p.is_dir():
                out[rel] = "dir"
            elif p.is_file():
                out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
            else:
                out[rel] = f"mode {stat.S_IFMT(p.lstat().st_mode):o}"
    return out


def refused(root: Path, argv: list[str], expect: str) -> str:
    """Run `skyeyes-bench ARGV`: exit 2, one line holding `expect`, nothing under `root` changed."""
    before = snapshot(root)
    _, out, err = run_cli(*argv, check=2)
    assert err.count("\n") == 1 and err.startswith("skyeyes-bench: error: "), err
    assert "Traceback" not in err and expect in err, err
    assert snapshot(root) == before
    return err


def _scene_copy(w: Path, tmp: Path) -> Path:
    ds = tmp / "ds"
    shutil.copytree(w / "ds", ds)
    return ds


# --------------------------------------------------------------------------- 1. never an input, --force by kind

_T = ["submission", "template", "--data"]
_EV = ["evaluate", "--allow-missing", "{w}/sub", "--data", "{w}/ds", "--quiet"]
CASES = {
    # submission template --out: the dataset, its parent, inside it, a link to it; --force only over a submission
    "template-out-is-dataset": ([*_T, "{w}/ds", "--out", "{w}/ds", "--force"], "ds: is the dataset"),
    "template-out-parent": ([*_T, "{w}/ds", "--out", "{w}", "--force"], "holds"),
    "template-out-inside": ([*_T, "{w}/ds", "--out", "{w}/ds/test-0-lane00", "--force"], "lies inside"),
    "template-out-link": ([*_T, "{w}/ds", "--out", "{w}/ds-link", "--force"], "ds-link: is the dataset"),
    "template-force-other": ([*_T, "{w}/ds", "--out", "{w}/home", "--force"], "is not a submission folder"),
    "template-force-file": ([*_T, "{w}/ds", "--out", "{w}/notes.txt", "--force"], "notes.txt: is a file"),
    "template-gt-out-is-dataset": ([*_T, "{w}/ds", "--out", "{w}/ds", "--force", "--from-ground-truth"],
                                   "is the dataset"),
    # importers: OUT is SRC, its parent, inside it; --force only over a dataset
    "carla-out-is-src": (["data", "import-carla", "{w}/carla", "{w}/carla", "--force"], "is the capture"),
    "carla-out-parent": (["data", "import-carla", "{w}/carla", "{w}", "--force"], "holds"),
    "carla-out-inside": (["data", "import-carla", "{w}/carla", "{w}/carla/ds"], "lies inside"),
    "carla-force-other": (["data", "import-carla", "{w}/carla", "{w}/home", "--force"], "is not a dataset folder"),
    "mc-out-is-src": (["data", "import-matrixcity", "{w}/mc", "{w}/mc", "--force"], "is the capture"),
    "mc-out-parent": (["data", "import-matrixcity", "{w}/mc", "{w}", "--force"], "holds"),
    "mc-out-inside": (["data", "import-matrixcity", "{w}/mc", "{w}/mc/street/ds"], "lies inside"),
    "mc-force-other": (["data", "import-matrixcity", "{w}/mc", "{w}/home", "--force"], "is not a dataset folder"),
    "synthtown-force-other": (["data", "synthtown", "--preset", "smoke", "--out", "{w}/home", "--force", "--quiet"],
                              "is not a dataset folder"),
    "gallery-out-inside": (["data", "gallery", "--dataset", "{w}/ds", "--out", "{w}/ds/g.png"], "lies inside"),
    # merge --out: a part, or a path whose sidecar is a part's sidecar
    "merge-out-is-part": (["merge", "{w}/p0.json", "{w}/p1.json", "--out", "{w}/p0.json", "--force"], "p0.json: is"),
    "merge-sidecar-is-parts": (["merge", "{w}/p0.json", "{w}/p1.json", "--out", "{w}/p0", "--force"],
                               "p0.features.npz: is one of the parts"),
    "merge-force-other": (["merge", "{w}/p0.json", "{w}/p1.json", "--out", "{w}/notes.txt", "--force"],
                          "is not a results file"),
    "merge-out-dot": (["merge", "{w}/p0.json", "{w}/p1.json", "--out", ".", "--force"], "is a folder"),
    # evaluate --out: inside the submission or the dataset, one of their files, not a results file
    "ev-out-inside-sub": ([*_EV, "--out", "{w}/sub/r.json"], "lies inside"),
    "ev-out-dataset-file": ([*_EV, "--out", "{w}/ds/dataset.json", "--force"], "lies inside"),
    "ev-out-sidecar-is-dataset": ([*_EV, "--out", "{w}/ds/x", "--force"], "lies inside"),
    "ev-force-other": ([*_EV, "--out", "{w}/notes.txt", "--force"], "is not a results file"),
    "ev-out-dot": ([*_EV, "--out", "."], "is a folder"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_no_output_is_an_input_and_force_replaces_its_own_kind(w, case):
    argv, expect = CASES[case]
    link = w / "ds-link"
    link.symlink_to(w / "ds")
    try:
        refused(w, [a.format(w=w) for a in argv], expect)
    finally:
        link.unlink()


def test_force_replaces_an_earlier_output_of_the_same_kind(w, tmp_path):
    """A submission folder, a dataset and a results file are each replaced by --force (and an
    unrelated file beside the sidecar name is refused even so)."""
    sub, ds, res = tmp_path / "sub", tmp_path / "imported", tmp_path / "r.json"
    for _ in range(2):
        run_cli(*_T, str(w / "ds"), "--out", str(sub), "--force")
        run_cli("data", "import-carla", str(w / "carla"), str(ds), "--no-progress", "--force")
        run_cli("evaluate", "--allow-missing", str(w / "sub"), "--data", str(w / "ds"), "--out", str(res), "--quiet", "--force")
    assert (sub / "submission.json").is_file() and (ds / "dataset.json").is_file()
    # a sidecar without arrays (every set metric unavailable) is an empty zip: still recognised
    (tmp_path / "e.features.npz").write_bytes(outputunit.npz_bytes({}))
    assert FEATURES_OUTPUT.recognises(tmp_path / "e.features.npz")
    (tmp_path / "s.features.npz").write_text("my notes\n")
    refused(tmp_path, ["evaluate", "--allow-missing", str(w / "sub"), "--data", str(w / "ds"), "--out", str(tmp_path / "s.json"),
                       "--quiet", "--force"], "s.features.npz: exists and is not a features sidecar")


def test_capture_force_never_deletes_the_waypoints_it_reads(tmp_path):
    """`capture-carla --force` starts over by deleting OUT: never while a file it reads lies there."""
    from builders.carla_capture import waypoints_json

    out = tmp_path / "cap"
    base = ["data", "capture-carla", "--town", "Town04", "--out", str(out), "--plan-only", "--min-points", "4"]
    run_cli(*base, "--waypoints", str(_write(tmp_path / "w.json", waypoints_json())))
    _write(out / "mine.json", waypoints_json())
    refused(tmp_path, [*base[:-1], "7", "--force", "--waypoints", str(out / "mine.json")],
            "mine.json: lies inside")


def _write(path: Path, doc) -> Path:
    path.write_text(json.dumps(doc))
    return path


# --------------------------------------------------------------------------- 2. one unit: concurrent and killed runs


def _env(world: Path) -> dict:
    return {**os.environ, "SKYEYES_PROTOCOLS": str(world / "protocols"), "SKYEYES_CACHE": str(world / "cache")}


def _evaluate_argv(w: Path, out: Path, *extra: str) -> list[str]:
    return ["evaluate", "--allow-missing", str(w / "sub"), "--data", str(w / "ds"), "--out", str(out), "--quiet", *extra]


def _unit(out: Path) -> tuple[dict, bytes]:
    """(results without their wall-clock timings, sidecar bytes), after checking they agree."""
    doc = json.loads(out.read_text())
    blob = out.with_name(out.name[:-len(".json")] + ".features.npz").read_bytes()
    assert doc["features"]["sha256"] == hashlib.sha256(blob).hexdigest()
    doc.pop("timing_s")
    return doc, blob


def _clean_folder(folder: Path, *names: str) -> None:
    """No lock file and no temporary file left: only `names`."""
    assert sorted(os.listdir(folder)) == sorted(names)


def test_two_runs_to_one_out_leave_one_intact_unit(world, w, tmp_path):
    out, before = tmp_path / "r.json", snapshot(w)
    cmd = [sys.executable, "-m", "skyeyes_bench.cli", *_evaluate_argv(w, out)]
    procs = [subprocess.Popen(cmd, env=_env(world), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    done = [(p.wait(timeout=120), *p.communicate()) for p in procs]
    codes = sorted(rc for rc, _, _ in done)
    assert codes in ([0, 2], [0, 0]), done
    for rc, _, err in done:
        if rc == 2:
            assert err.count("\n") == 1 and ("another run is writing it" in err or "already exists" in err), err
    _unit(out)
    _clean_folder(tmp_path, "r.json", "r.features.npz")
    assert snapshot(w) == before


#: Runs `skyeyes-bench ARGS` and stops for good at one point of `outputunit.write_unit` (marker file
#: written), where the test kills it with SIGKILL.
_DRIVER = r'''
import os, sys, time
point, marker, name = sys.argv[1], sys.argv[2], sys.argv[3]
real_replace, real_unlink = os.replace, os.unlink
def stop():
    open(marker, "w").close()
    time.sleep(300)
def replace(src, dst, *a, **k):
    if point == "before-renames" and str(src).endswith(".partial"):
        stop()
    real_replace(src, dst, *a, **k)
    if point == "after-sidecar" and str(dst).endswith(".features.npz"):
        stop()
def unlink(path, *a, **k):
    real_unlink(path, *a, **k)
    if point == "after-old-removed" and os.path.basename(str(path)) == name:
        stop()
os.replace, os.unlink = replace, unlink
from skyeyes_bench.cli import main
sys.exit(main(sys.argv[4:]))
'''


@pytest.mark.parametrize("point", ["before-renames", "after-sidecar", "after-old-removed"])
def test_killed_run_repeats_without_force_to_the_same_bytes(world, w, tmp_path, point):
    out_dir = tmp_path / "o"
    out = out_dir / "r.json"
    run_cli(*_evaluate_argv(w, out))
    want = _unit(out)  # the uninterrupted run
    if point != "after-old-removed":  # else: the killed run replaces an earlier unit with --force
        shutil.rmtree(out_dir)
    marker, before = tmp_path / "stopped", snapshot(w)
    argv = _evaluate_argv(w, out, *(["--force"] if point == "after-old-removed" else []))
    proc = subprocess.Popen([sys.executable, "-c", _DRIVER, point, str(marker), out.name, *argv], env=_env(world),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    while not marker.exists():
        assert proc.poll() is None, proc.communicate()[1]
        assert time.monotonic() - t0 < 120
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not out.exists()  # killed before its results were renamed in: no output yet
    run_cli(*_evaluate_argv(w, out))  # no --force
    assert _unit(out) == want
    _clean_folder(out_dir, "r.json", "r.features.npz")
    assert snapshot(w) == before


@pytest.mark.parametrize("member", [".features.npz.", ".json."])
def test_full_disk_during_evaluate_is_one_line_and_writes_nothing(w, tmp_path, monkeypatch, member):
    """ENOSPC while writing the sidecar, or the results after the sidecar: one line, exit 2, no file."""
    real = os.write

    def write(fd, data):
        if member in os.readlink(f"/proc/self/fd/{fd}") and ".partial" in os.readlink(f"/proc/self/fd/{fd}"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(fd, data)

    monkeypatch.setattr(os, "write", write)
    err = refused(tmp_path, _evaluate_argv(w, tmp_path / "r.json"), "No space left on device")
    assert "r.json: cannot write" in err
    assert os.listdir(tmp_path) == []


# --------------------------------------------------------------------------- 3. the user's umask


def test_files_and_folders_get_the_users_umask(w, tmp_path):
    old = os.umask(0o027)
    try:
        run_cli(*_T, str(w / "ds"), "--out", str(tmp_path / "sub"), "--from-ground-truth")
        run_cli("data", "import-carla", str(w / "carla"), str(tmp_path / "ds"), "--no-progress")
        run_cli(*_evaluate_argv(w, tmp_path / "r.json"))
    finally:
        os.umask(old)
    modes = {stat.S_IMODE(p.lstat().st_mode) for p in tmp_path.rglob("*") if p.is_file()}
    folders = {stat.S_IMODE(p.lstat().st_mode) for p in [tmp_path / "sub", *tmp_path.rglob("*")] if p.is_dir()}
    assert modes == {0o640} and folders == {0o750}, (modes, folders)


# --------------------------------------------------------------------------- 4. no traceback, no hang


def test_protocol_fifo_and_huge_versions_are_one_line(world, tmp_path):
    protos = tmp_path / "protocols"
    shutil.copytree(world / "protocols", protos)
    (protos / "piped").mkdir()
    os.mkfifo(protos / "piped" / "v1.toml")
    (protos / "huge").mkdir()
    text = TEST_PROTOCOL.replace('id = "evaltest"', 'id = "huge"')
    (protos / "huge" / "v1.toml").write_text(text.replace("version = 1", f"version = {NINES}"))
    (protos / "long").mkdir()
    (protos / "long" / "v1.toml").write_text(text.replace('"huge"', '"long"').replace("version = 1",
                                                                                   f"version = {NINES[:4000]}"))
    env = {**os.environ, "SKYEYES_PROTOCOLS": str(protos)}
    for ref, expect in (("piped", "is a named pipe"), ("huge", "not valid TOML here"),
                        ("long", "key 'version' must be an int >= 1"), (f"synthtown@{NINES}", "5000 digits")):
        r = subprocess.run([sys.executable, "-m", "skyeyes_bench.cli", "protocols", "show", ref], env=env,
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == 2 and r.stderr.count("\n") == 1 and expect in r.stderr, (ref, r.stderr[:300])
        assert len(r.stderr) < 600


@pytest.mark.parametrize("radius", ["nan", "-5", "0", "inf"])
def test_aerial_radius_must_be_a_positive_distance(w, tmp_path, radius):
    refused(w, ["data", "import-matrixcity", str(w / "mc"), str(tmp_path / "out"), f"--aerial-radius={radius}",
                "--no-progress"], "--aerial-radius")
    assert not (tmp_path / "out").exists()


def _mc_link_image(mc, w):
    img = mc / "street" / "train" / "road_a" / "0000.png"
    img.unlink()
    img.symlink_to(w / "outside.png")


def _mc_link_depth(mc, w):
    d = mc / "street" / "train" / "road_a_depth" / "0000.exr"
    shutil.copyfile(d, w.parent / "depth.exr")
    d.unlink()
    d.symlink_to(w.parent / "depth.exr")


def _mc_link_poses(mc, w):
    j = mc / "aerial" / "train" / "block_1" / "transforms.json"
    shutil.copyfile(j, w.parent / "transforms.json")
    j.unlink()
    j.symlink_to(w.parent / "transforms.json")


@pytest.mark.parametrize("link", [_mc_link_image, _mc_link_depth, _mc_link_poses], ids=lambda f: f.__name__[9:])
def test_matrixcity_refuses_symlinks_out_of_src(w, tmp_path, link):
    mc = tmp_path / "mc"
    shutil.copytree(w / "mc", mc, symlinks=True)
    link(mc, w)
    refused(tmp_path, ["data", "import-matrixcity", str(mc), str(tmp_path / "out"), "--no-progress"], "leaves")


def _ds_link_scene(ds, away):
    shutil.move(ds / "test-0-lane00", away / "scene")
    (ds / "test-0-lane00").symlink_to(away / "scene")


def _ds_link_folder(ds, away):
    shutil.move(ds / "test-0-lane01" / "ground", away / "ground")
    (ds / "test-0-lane01" / "ground").symlink_to(away / "ground")


def _ds_link_frame(ds, away):
    f = ds / "test-0-lane01" / "ground" / "000001.png"
    shutil.move(f, away / "frame.png")
    f.symlink_to(away / "frame.png")


@pytest.mark.parametrize("link", [_ds_link_scene, _ds_link_folder, _ds_link_frame], ids=lambda f: f.__name__[9:])
@pytest.mark.parametrize("command", ["check", "template"])
def test_dataset_folders_linked_outside_are_refused(w, tmp_path, link, command):
    ds, away = _scene_copy(w, tmp_path), tmp_path / "away"
    away.mkdir()
    link(ds, away)
    argv = ["data", "check", str(ds)] if command == "check" else [*_T, str(ds), "--out", str(tmp_path / "sub")]
    refused(tmp_path, argv, "leaves the dataset folder")
