"""Issue 14: a malformed-input corpus per command (evaluate, data check, submission template,
both importers, merge, compare), generated here. Every case must exit 2 with one line naming
the file (and field), no traceback, nothing written, within seconds, under a memory limit.

All cases run in one subprocess (`_hostile_runner.py`) with RLIMIT_AS and a per-case alarm, so
a memory blow-up or a hang is a failing case, not a dead test session.
"""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from builders.captures import make_carla, make_matrixcity
from builders.evaluation import TEST_PROTOCOL, blurred_submission, make_dataset
from conftest import ROOT

HERE = Path(__file__).resolve().parent
MEMORY = 6 << 30  # the address space torch's import needs, plus room; an unbounded set is not
SECONDS = 30  # per case, on a shared, noisy 2-core machine; real cases take well under 5 s


def _snapshot(root: Path) -> dict[str, tuple]:
    """Every path under root with its type, size and mtime (named pipes included)."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            st = p.lstat()
            out[str(p.relative_to(root))] = (st.st_mode, st.st_size, st.st_mtime_ns)
    return out


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """Valid inputs for every command: a tiny dataset, a submission of it, results and shard
    partials of two submissions with byte-identical submission.json, CARLA and MatrixCity captures."""
    base = tmp_path_factory.mktemp("world")
    env = {**os.environ, "SKYEYES_PROTOCOLS": str(base / "protocols"), "SKYEYES_CACHE": str(base / "cache")}
    shutil.copytree(ROOT / "protocols", base / "protocols")
    (base / "protocols" / "evaltest").mkdir()
    (base / "protocols" / "evaltest" / "v1.toml").write_text(TEST_PROTOCOL)
    mp = pytest.MonkeyPatch()
    try:
        mp.setenv("SKYEYES_PROTOCOLS", env["SKYEYES_PROTOCOLS"])
        mp.setenv("SKYEYES_CACHE", env["SKYEYES_CACHE"])
        from skyeyes_bench.data.layout import open_dataset
        from skyeyes_bench.evaluate import evaluate

        w = base / "w"
        ds = open_dataset(make_dataset(w / "ds", scenes=2, seqs=1, frames=4))
        sub = blurred_submission(ds, w / "sub", sigma=0.7)
        other = w / "other"  # same submission.json, one frame different
        shutil.copytree(sub, other)
        f0 = sorted((other / "test-0-lane01" / "ground").glob("*.png"))[0]
        shutil.copyfile(sorted((sub / "test-0-lane00" / "ground").glob("*.png"))[1], f0)
        evaluate(sub, data=w / "ds", out=w / "res.json", progress=False)
        evaluate(sub, data=w / "ds", out=w / "p0.json", shard="0/2", progress=False)
        evaluate(other, data=w / "ds", out=w / "q1.json", shard="1/2", progress=False)
        make_carla(w / "carla")
        make_matrixcity(w / "mc", depth=False)
        make_matrixcity(w / "mcp", depth=False, paper=True)
    finally:
        mp.undo()
    (w / "outside.png").write_bytes((w / "carla" / "rgb" / "000000.png").read_bytes())
    return base, env


def _json_edit(path: Path, fn):
    raw = json.loads(path.read_text())
    fn(raw)
    path.write_text(json.dumps(raw))


def _text(path: Path, text: str):
    path.write_text(text)


def _fifo(path: Path):
    path.unlink(missing_ok=True)
    if path.is_dir():
        shutil.rmtree(path)
    os.mkfifo(path)


def _folder(path: Path):
    path.unlink()
    path.mkdir()


def _scene(w):
    return w / "ds" / "test-0-lane00" / "scene.json"


def _frame(w):
    return w / "sub" / "test-0-lane00" / "ground" / "000000.png"


def _manifest(w):
    return w / "sub" / "submission.json"


def _set(key, value):
    def fn(raw):
        *head, last = key.split(".")
        d = raw
        for k in head:
            d = d[k] if not k.isdigit() else d[int(k)]
        d[last if not last.isdigit() else int(last)] = value
    return fn


def _ev(w, *extra):
    return ["evaluate", "--allow-missing", str(w / "sub"), "--data", str(w / "ds"), "--quiet", *extra]


def _check(w):
    return ["data", "check", str(w / "ds")]


def _carla(w):
    return ["data", "import-carla", str(w / "carla"), str(w / "imported"), "--no-progress"]


def _mc(w, src="mc"):
    return ["data", "import-matrixcity", str(w / src), str(w / "imported"), "--town", "region5", "--no-progress"]


def _mc_json(w, src="mc"):
    return sorted((w / src).rglob("transforms*.json"))[0]


def _deep(path: Path):
    path.write_text("[" * 100_000 + "]" * 100_000)


def _sparse(path: Path):
    path.unlink(missing_ok=True)
    with open(path, "wb") as f:
        f.truncate(300 << 20)  # 300 MB of holes: size alone must refuse it


# id -> (mutate(w), argv(w), what stderr must name). Every case is one bad thing in valid input.
CASES = {
    # ------------------------------------------------------------------ evaluate: submission.json
    "ev-nan-timing": (lambda w: _text(_manifest(w), _manifest(w).read_text().replace('"fit_s": 1.0', '"fit_s": NaN')),
                      _ev, "field 'timings.fit_s' is nan"),
    "ev-inf-timing": (lambda w: _text(_manifest(w), _manifest(w).read_text().replace('"render_s": 2.0', '"render_s": 1e400')),
                      _ev, "field 'timings.render_s' is inf"),
    "ev-negative-timing": (lambda w: _json_edit(_manifest(w), _set("timings.fit_s", -1)), _ev, "field 'timings.fit_s'"),
    "ev-bool-memory": (lambda w: _json_edit(_manifest(w), _set("peak_memory_mb", True)), _ev, "field 'peak_memory_mb'"),
    "ev-string-per-frame": (lambda w: _json_edit(_manifest(w), _set("timings.per_frame_render_s", ["1"])), _ev,
                            "field 'timings.per_frame_render_s'"),
    "ev-method-slash": (lambda w: _json_edit(_manifest(w), _set("method", "a/b")), _ev, "field 'method'"),
    "ev-method-dotdot": (lambda w: _json_edit(_manifest(w), _set("method", "..")), _ev, "field 'method'"),
    "ev-method-nul": (lambda w: _json_edit(_manifest(w), _set("method", "a\x00b")), _ev, "field 'method'"),
    "ev-sha-number": (lambda w: _json_edit(_manifest(w), _set("protocol_sha256", 12345)), _ev, "field 'protocol_sha256'"),
    "ev-protocol-number": (lambda w: _json_edit(_manifest(w), _set("protocol", 7)), _ev, "field 'protocol'"),
    "ev-dataset-list": (lambda w: _json_edit(_manifest(w), _set("dataset", [])), _ev, "field 'dataset.name'"),
    "ev-not-utf8": (lambda w: _manifest(w).write_bytes(b'{"method": "\xff\xfe"}'), _ev, "not UTF-8"),
    "ev-deep": (lambda w: _deep(_manifest(w)), _ev, "nested"),
    "ev-huge-int": (lambda w: _text(_manifest(w), '{"a": ' + "9" * 5000 + "}"), _ev, "submission.json"),
    "ev-sparse-300mb": (lambda w: _sparse(_manifest(w)), _ev, "bytes, more than"),
    "ev-manifest-folder": (lambda w: _folder(_manifest(w)), _ev, "submission.json"),
    "ev-manifest-fifo": (lambda w: _fifo(_manifest(w)), _ev, "submission.json"),
    # ------------------------------------------------------------------ evaluate: frames
    "ev-frame-fifo": (lambda w: _fifo(_frame(w)), _ev, "000000.png: is a named pipe"),
    "ev-frame-truncated": (lambda w: _frame(w).write_bytes(_frame(w).read_bytes()[:60]), _ev, "000000.png"),
    "ev-frame-bad-crc": (lambda w: _frame(w).write_bytes(_frame(w).read_bytes()[:-20] + b"\x00" + _frame(w).read_bytes()[-19:]),
                         _ev, "000000.png"),
    "ev-frame-escapes": (lambda w: (_frame(w).unlink(), _frame(w).symlink_to(w / "outside.png")), _ev, "000000.png"),
    # ------------------------------------------------------------------ evaluate: outputs, shards, dataset
    "ev-out-inside-sub": (lambda w: None, lambda w: _ev(w, "--out", str(w / "sub" / "r.json")), "lies inside"),
    "ev-out-parent-file": (lambda w: (w / "afile").write_text("x"),
                           lambda w: _ev(w, "--out", str(w / "afile" / "r.json")), "afile is a file"),
    "ev-out-sidecar-exists": (lambda w: (w / "r.features.npz").write_bytes(b"x"),
                              lambda w: _ev(w, "--out", str(w / "r.json")), "r.features.npz: already exists"),
    "ev-out-folder-force": (lambda w: (w / "rdir.json").mkdir(),
                            lambda w: _ev(w, "--out", str(w / "rdir.json"), "--force"), "rdir.json: is a folder"),
    "ev-out-inside-data": (lambda w: None, lambda w: _ev(w, "--out", str(w / "ds" / "r.json")), "lies inside"),
    "ev-shard-huge": (lambda w: None, lambda w: _ev(w, "--shard", "0/999999999999"), "--shard 0/999999999999"),
    "ev-shard-junk": (lambda w: None, lambda w: _ev(w, "--shard", "a/b"), "--shard"),
    "ev-data-scene-dotdot": (lambda w: _json_edit(w / "ds" / "dataset.json", _set("scenes.1", "..")), _ev,
                             "field 'scenes[1]'"),
    # ------------------------------------------------------------------ data check
    "ds-scene-dotdot": (lambda w: _json_edit(w / "ds" / "dataset.json", _set("scenes.0", "..")), _check, "field 'scenes[0]'"),
    "ds-scene-slash": (lambda w: _json_edit(w / "ds" / "dataset.json", _set("scenes.0", "a/../../b")), _check,
                       "field 'scenes[0]'"),
    "ds-scene-nul": (lambda w: _json_edit(w / "ds" / "dataset.json", _set("scenes.0", "a\x00")), _check, "field 'scenes[0]'"),
    "ds-scenes-number": (lambda w: _json_edit(w / "ds" / "dataset.json", _set("scenes", 3)), _check, "field 'scenes'"),
    "ds-index-huge": (lambda w: _json_edit(_scene(w), _set("ground.1.index", 10**12)), _check, "field 'index'"),
    "ds-index-float": (lambda w: _json_edit(_scene(w), _set("ground.1.index", 1.5)), _check, "field 'index'"),
    "ds-sequence-dotdot": (lambda w: _json_edit(_scene(w), _set("ground.0.sequence", "../x")), _check, "field 'sequence'"),
    "ds-width-inf": (lambda w: _text(_scene(w), _scene(w).read_text().replace('"width": 32', '"width": 1e400', 1)), _check,
                     "intrinsics.ground.width' is inf"),
    "ds-fx-nan": (lambda w: _text(_scene(w), _scene(w).read_text().replace('"fx": 16.0', '"fx": NaN', 1)), _check,
                  "intrinsics.ground.fx' is nan"),
    "ds-width-huge": (lambda w: _json_edit(_scene(w), _set("intrinsics.ground.width", 10**12)), _check,
                      "field 'intrinsics.ground'"),
    "ds-fx-string": (lambda w: _json_edit(_scene(w), _set("intrinsics.ground.fx", "16")), _check,
                     "field 'intrinsics.ground'"),
    "ds-c2w-strings": (lambda w: _json_edit(_scene(w), _set("ground.0.c2w", [["1", "0", "0", "0"]] * 4)), _check,
                       "field 'c2w'"),
    "ds-file-escape": (lambda w: _json_edit(_scene(w), _set("ground.0.file", "ground/../../../x.png")), _check,
                       "field 'file'"),
    "ds-file-absolute": (lambda w: _json_edit(_scene(w), _set("ground.0.file", "/etc/hostname")), _check, "field 'file'"),
    "ds-scene-not-utf8": (lambda w: _scene(w).write_bytes(b"\xc3\x28"), _check, "scene.json: not UTF-8"),
    "ds-dataset-deep": (lambda w: _deep(w / "ds" / "dataset.json"), _check, "dataset.json"),
    "ds-dataset-fifo": (lambda w: _fifo(w / "ds" / "dataset.json"), _check, "dataset.json"),
    "ds-dataset-folder": (lambda w: _folder(w / "ds" / "dataset.json"), _check, "dataset.json"),
    "ds-frame-fifo": (lambda w: _fifo(w / "ds" / "test-0-lane00" / "ground" / "000001.png"), _check, "000001.png"),
    # ------------------------------------------------------------------ submission template
    "tpl-scene-dotdot": (lambda w: _json_edit(w / "ds" / "dataset.json", _set("scenes.1", "..")),
                         lambda w: ["submission", "template", "--data", str(w / "ds"), "--out", str(w / "tpl" / "s"),
                                    "--from-ground-truth"], "field 'scenes[1]'"),
    "tpl-out-parent-file": (lambda w: (w / "afile").write_text("x"),
                            lambda w: ["submission", "template", "--data", str(w / "ds"), "--out",
                                       str(w / "afile" / "s")], "afile is a file"),
    # ------------------------------------------------------------------ import-carla
    "carla-out-parent-file": (lambda w: (w / "afile").write_text("x"),
                              lambda w: ["data", "import-carla", str(w / "carla"), str(w / "afile" / "x" / "out"),
                                         "--no-progress"], "afile is a file"),
    "carla-index-huge": (lambda w: _json_edit(w / "carla" / "capture.json", _set("frames.0.index", 10**12)), _carla,
                         "frames[0].index"),
    "carla-capture-folder": (lambda w: _folder(w / "carla" / "capture.json"), _carla, "capture.json"),
    "carla-capture-fifo": (lambda w: _fifo(w / "carla" / "capture.json"), _carla, "capture.json"),
    "carla-not-utf8": (lambda w: (w / "carla" / "capture.json").write_bytes(b"\x80"), _carla, "not UTF-8"),
    "carla-image-escapes": (lambda w: _json_edit(w / "carla" / "capture.json", _set("frames.0.image", "../outside.png")),
                            _carla, "frames[0].image"),
    "carla-image-fifo": (lambda w: _fifo(w / "carla" / "rgb" / "000000.png"), _carla, "frames[0].image"),
    "carla-rotation-strings": (lambda w: _json_edit(w / "carla" / "capture.json", _set("frames.0.rotation", ["0", "1", "2"])),
                               _carla, "frames[0].rotation"),
    "carla-fov-nan": (lambda w: _text(w / "carla" / "capture.json",
                                      (w / "carla" / "capture.json").read_text().replace('"fov": 90.0', '"fov": NaN', 1)),
                      _carla, "frames[0].fov' is nan"),
    "carla-town-dotdot": (lambda w: _json_edit(w / "carla" / "capture.json", _set("frames.0.town", "..")), _carla,
                          "frames[0].town"),
    # ------------------------------------------------------------------ import-matrixcity
    "mc-transforms-folder": (lambda w: _folder(_mc_json(w)), _mc, "transforms.json"),
    "mc-rot-strings": (lambda w: _json_edit(_mc_json(w), _set("frames.0.rot_mat", [["1", "0", "0", "0"]] * 4)), _mc,
                       "frames[0].rot_mat"),
    "mc-rot-letters": (lambda w: _json_edit(_mc_json(w), _set("frames.0.rot_mat", [["a"] * 4] * 4)), _mc,
                       "frames[0].rot_mat"),
    "mc-angle-string": (lambda w: _json_edit(_mc_json(w), _set("camera_angle_x", "wide")), _mc, "camera_angle_x"),
    "mc-paper-escape": (lambda w: _json_edit(_mc_json(w, "mcp"), _set("frames.0.file_path", "../../../../../outside.png")),
                        lambda w: _mc(w, "mcp"), "frames[0].file_path"),
    "mc-paper-w-string": (lambda w: _json_edit(_mc_json(w, "mcp"), _set("w", "x")), lambda w: _mc(w, "mcp"), "field 'w'"),
    # ------------------------------------------------------------------ merge
    "merge-other-frames": (lambda w: None, lambda w: ["merge", str(w / "p0.json"), str(w / "q1.json"), "--out",
                                                      str(w / "m.json"), "--quiet"], "frames_sha256"),
    "merge-count-huge": (lambda w: _json_edit(w / "p0.json", _set("shard.count", 999999999999)),
                         lambda w: ["merge", str(w / "p0.json"), "--out", str(w / "m.json")], "field 'shard.count'"),
    "merge-index-string": (lambda w: _json_edit(w / "p0.json", _set("shard.index", "0")),
                           lambda w: ["merge", str(w / "p0.json"), "--out", str(w / "m.json")], "field 'shard.index'"),
    "merge-sequence-huge": (lambda w: _json_edit(w / "p0.json", _set("frames.0.sequence", 10**9)),
                            lambda w: ["merge", str(w / "p0.json"), "--out", str(w / "m.json")], "frames[0].sequence"),
    "merge-sidecar-escape": (lambda w: _json_edit(w / "p0.json", _set("features.file", "../p0.features.npz")),
                             lambda w: ["merge", str(w / "p0.json"), "--out", str(w / "m.json")], "features.file"),
    "merge-not-utf8": (lambda w: (w / "p0.json").write_bytes(b"\xff"),
                       lambda w: ["merge", str(w / "p0.json"), "--out", str(w / "m.json")], "p0.json: not UTF-8"),
    "merge-out-parent-file": (lambda w: (w / "afile").write_text("x"),
                              lambda w: ["merge", str(w / "p0.json"), "--out", str(w / "afile" / "m.json")],
                              "afile is a file"),
    "merge-out-is-part": (lambda w: None, lambda w: ["merge", str(w / "p0.json"), "--out", str(w / "p0.json"), "--force"],
                          "p0.json"),
    # ------------------------------------------------------------------ compare
    "cmp-folder": (lambda w: _folder(w / "res.json"), lambda w: ["compare", str(w / "res.json"), str(w / "res.json")],
                   "res.json"),
    "cmp-metrics-list": (lambda w: _json_edit(w / "res.json", _set("metrics", [])),
                         lambda w: ["compare", str(w / "res.json"), str(w / "res.json")], "field 'metrics'"),
    "cmp-sequences-strings": (lambda w: _json_edit(w / "res.json", _set("dataset.sequences", [1, 2])),
                              lambda w: ["compare", str(w / "res.json"), str(w / "res.json")], "dataset.sequences[0]"),
    "cmp-psnr-string": (lambda w: _json_edit(w / "res.json", _set("frames.0.psnr", "high")),
                        lambda w: ["compare", str(w / "res.json"), str(w / "res.json")], "frames[0].psnr"),
    "cmp-kind-empty": (lambda w: _json_edit(w / "res.json", _set("metrics.ssim.kind", "")),  # found by the fuzz
                       lambda w: ["compare", str(w / "res.json"), str(w / "res.json")], "field 'metrics.ssim.kind'"),
    "cmp-sequence-value-missing": (lambda w: _json_edit(w / "res.json", lambda r: r["sequences"].popitem()),
                                   lambda w: ["compare", str(w / "res.json"), str(w / "res.json")], "field 'sequences."),
    "cmp-out-parent-file": (lambda w: (w / "afile").write_text("x"),
                            lambda w: ["compare", str(w / "res.json"), str(w / "res.json"), "--out", str(w / "afile" / "c.json")],
                            "afile is a file"),
    "cmp-out-is-input": (lambda w: None, lambda w: ["compare", str(w / "res.json"), str(w / "res.json"), "--out",
                                                   str(w / "res.json")], "res.json: is one of the results"),
}


def test_every_hostile_case_exits_2_with_one_line_and_writes_nothing(world, tmp_path):
    base, env = world
    plan, snaps = [], {}
    for cid, (mutate, argv, _) in CASES.items():
        w = tmp_path / cid
        shutil.copytree(base / "w", w, symlinks=True)
        mutate(w)
        snaps[cid] = _snapshot(w)
        plan.append({"id": cid, "argv": argv(w)})
    (tmp_path / "cases.json").write_text(json.dumps(plan))
    report = tmp_path / "report.jsonl"
    proc = subprocess.run([sys.executable, str(HERE / "_hostile_runner.py"), str(tmp_path / "cases.json"),
                           str(report), str(MEMORY), str(SECONDS)], env=env, capture_output=True, text=True,
                          timeout=SECONDS * len(CASES) + 120)
    got = {r["id"]: r for r in map(json.loads, report.read_text().splitlines())} if report.exists() else {}
    failures = []
    if proc.returncode != 0:
        failures.append(f"runner died (rc {proc.returncode}) after {len(got)} cases: {proc.stderr[-2000:]}")
    for cid, (_, _, must) in CASES.items():
        r = got.get(cid)
        if r is None:
            failures.append(f"{cid}: not run")
            continue
        err = r["stderr"]
        lines = err.strip().splitlines()
        why = []
        if r["exc"]:
            why.append(f"raised: {r['exc'][-600:]}")
        if r["rc"] != 2:
            why.append(f"exit {r['rc']}")
        if len(lines) != 1 or not lines[0].startswith("skyeyes-bench: error: "):
            why.append(f"stderr is not one error line: {err[-600:]!r}")
        if must not in err:
            why.append(f"stderr does not name {must!r}: {err[-400:]!r}")
        if "Traceback" in err or "libpng" in err:
            why.append("traceback or a library's own line on stderr")
        if r["seconds"] > 20:
            why.append(f"took {r['seconds']:.1f} s")
        after = _snapshot(tmp_path / cid)
        if after != snaps[cid]:
            changed = sorted(set(after) ^ set(snaps[cid]) | {k for k in after if after.get(k) != snaps[cid].get(k)})
            why.append(f"wrote or changed {changed[:5]}")
        if why:
            failures.append(f"{cid}: " + "; ".join(why))
    assert not failures, f"{len(failures)} of {len(CASES)} hostile cases mishandled:\n" + "\n".join(failures)


def test_the_corpus_inputs_are_valid_before_mutation(world, tmp_path):
    """The mutations are the only thing wrong: the untouched world passes every command."""
    base, env = world
    w = tmp_path / "w"
    shutil.copytree(base / "w", w, symlinks=True)
    for argv in (_check(w), _carla(w), ["merge", str(w / "p0.json"), str(w / "q1.json"), "--out", str(w / "m.json")]):
        rc = subprocess.run([sys.executable, "-c", "from skyeyes_bench.cli import main; raise SystemExit(main())",
                             *argv], env=env, capture_output=True, text=True)
        if argv[0] == "merge":  # the two parts come from different frames: refused, but only for that
            assert rc.returncode == 2 and "frames_sha256" in rc.stderr, rc.stderr
        else:
            assert rc.returncode == 0, rc.stderr
