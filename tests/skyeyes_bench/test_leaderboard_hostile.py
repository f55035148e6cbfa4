"""Issue 35, the leaderboard: `leaderboard add` and `leaderboard [--check]` against hostile input.

Every hostile case must exit 2 with exactly one line on stderr, write nothing (inside or outside
the leaderboard folder: the snapshot of the whole test folder, siblings of the root included, is
unchanged) and destroy no input (the results file, the dataset and the submission it names).
Classes: fields that become paths (hashes, `protocol.ref`, names, committed `frames.json` tile
names and the test sequence's frames), a result named `ground-truth`, folders not its own, symlinks
planted to leave the root, saved animations that are not one (a link out, a pipe, not a WebP),
text that would break or spoof the page, run times and scores that are not numbers a page can
show, and a read-only root. Then what must work: the same odd text filed and escaped (Markdown
and HTML), files created with the user's umask, and stale plots removed only inside the root.
"""

import errno
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from builders.evaluation import blurred_submission, make_dataset, protocol_env
from conftest import ROOT, run_cli

#: A case that takes longer than this has hung (a real case takes well under a second).
SECONDS = 60


def _snapshot(*roots: Path) -> dict[str, tuple]:
    """Every path under the roots (links not followed) with its type/mode, size and mtime."""
    out = {}
    for root in roots:
        for dirpath, dirnames, filenames in os.walk(root):
            for name in dirnames + filenames:
                p = Path(dirpath) / name
                st = p.lstat()
                out[str(p)] = (st.st_mode, st.st_size, st.st_mtime_ns)
    return out


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A tiny dataset; a blurred submission of it (method 'blur') and its results; the ground
    truth as a submission (`submission template --from-ground-truth`, method 'ground-truth') and
    its results; a leaderboard folder (the reported tables) with 'blur' filed and its strip frames."""
    base = tmp_path_factory.mktemp("lbworld")
    with protocol_env(base):
        from skyeyes_bench.data.layout import open_dataset
        from skyeyes_bench.evaluate import evaluate

        ds = open_dataset(make_dataset(base / "ds", scenes=2, seqs=1, frames=4))
        blurred_submission(ds, base / "sub", sigma=0.7, method="blur")
        evaluate(base / "sub", data=ds.root, out=base / "res.json", progress=False)
        run_cli("submission", "template", "--data", str(ds.root), "--out", str(base / "gt-sub"), "--from-ground-truth")
        evaluate(base / "gt-sub", data=ds.root, out=base / "gt-res.json", progress=False)
        lb = base / "lb"
        shutil.copytree(ROOT / "leaderboard" / "reported", lb / "reported")
        run_cli("leaderboard", "add", str(base / "res.json"), "--root", str(lb))
    return base


class Case:
    """One test's folders: `tmp/parent/lb` (the root, a copy of the world's), siblings of the
    root that nothing may touch (`parent/blur`, named after the method; `parent/outside`), and
    `tmp/in` for hostile inputs."""

    def __init__(self, world: Path, tmp: Path):
        self.world, self.tmp = world, tmp
        self.parent = tmp / "parent"
        self.lb = self.parent / "lb"
        shutil.copytree(world / "lb", self.lb)
        for sibling in ("blur", "outside"):
            (self.parent / sibling).mkdir()
            (self.parent / sibling / "keep.txt").write_text("not the leaderboard's")
        (tmp / "in").mkdir()
        (self.key,) = [p.name for p in (self.lb / "frames").iterdir()]
        self.frames = self.lb / "frames" / self.key

    def results(self, edit=None, src: str = "res.json") -> Path:
        """A copy of the world's results file (in tmp/in), edited by `edit(doc)`."""
        doc = json.loads((self.world / src).read_text())
        if edit is not None:
            edit(doc)
        out = self.tmp / "in" / "r.json"
        out.write_text(json.dumps(doc))
        return out

    def filed(self, edit) -> None:
        """Edit the result filed in the root (`results/blur.json`), as a hand-edited commit would."""
        p = self.lb / "results" / "blur.json"
        doc = json.loads(p.read_text())
        edit(doc)
        p.write_text(json.dumps(doc))

    def add(self, *extra, edit=None, src="res.json") -> list[str]:
        return ["leaderboard", "add", str(self.results(edit, src)), "--root", str(self.lb), *extra]

    def page(self, *extra) -> list[str]:
        return ["leaderboard", "--root", str(self.lb), *extra]


@pytest.fixture
def case(world, tmp_path, monkeypatch):
    monkeypatch.setenv("SKYEYES_PROTOCOLS", str(world / "protocols"))
    c = Case(world, tmp_path)
    yield c
    os.chmod(c.lb, 0o755)  # a read-only case: let pytest clean up


def _set(key: str, value):
    def edit(doc):
        *head, last = key.split(".")
        d = doc
        for k in head:
            d = d[int(k)] if k.isdigit() else d[k]
        d[int(last) if last.isdigit() else last] = value
    return edit


def _tile(c: Case, name: str):
    p = c.frames / "frames.json"
    raw = json.loads(p.read_text())
    raw["frames"][0]["tile"] = name
    p.write_text(json.dumps(raw))


def _sequence(c: Case, key: str, value):
    """Edit the test sequence recorded in the committed frames.json."""
    p = c.frames / "frames.json"
    raw = json.loads(p.read_text())
    _set(key, value)(raw["sequence"])
    p.write_text(json.dumps(raw))


def _animation(c: Case, make):
    """Replace blur's saved animation (`frames/<key>/blur/sequence.webp`) with what `make(path)` puts there."""
    p = c.frames / "blur" / "sequence.webp"
    p.unlink()
    make(p)


def _reported(c: Case, old: str, new: str):
    p = c.lb / "reported" / "skyeyes-wacv2025-table1-citysample.toml"
    text = p.read_text()
    assert old in text
    p.write_text(text.replace(old, new, 1))


def _not_own(c: Case, name: str):
    """A strip folder `frames/<key>/<name>/` that no filed result owns (left there by hand)."""
    (c.frames / name).mkdir()
    (c.frames / name / "0.png").write_text("not add's")


def _link_outside(c: Case, sub: str):
    """Replace `<root>/<sub>` with a symlink to the root's sibling `outside/`."""
    p = c.lb / sub
    if p.is_dir():
        shutil.rmtree(p)
    p.symlink_to(c.parent / "outside", target_is_directory=True)


def _read_only(c: Case, monkeypatch):
    """The root made read-only. Root ignores permission bits, so there `os.access` answers for
    the folder as it would for anyone else."""
    os.chmod(c.lb, 0o555)
    if os.geteuid() == 0:
        real = os.access
        lb = c.lb.resolve()
        monkeypatch.setattr(os, "access", lambda p, mode, *a, **k: False if (
            mode & os.W_OK and Path(p).resolve() == lb) else real(p, mode, *a, **k))


def _read_only_late(c: Case, monkeypatch):
    """The file system refuses the first write (EROFS) although `os.access` said yes (a remount,
    a quota): the refusal at write time must be one line too."""
    import tempfile

    def refuse(*a, **k):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    monkeypatch.setattr(tempfile, "mkdtemp", refuse)


NEW = ("--name", "other")  # file under a name not yet taken
HUGE = "evaltest@" + "9" * 5000

# id -> (setup(case, monkeypatch) -> argv, text stderr must hold)
CASES = {
    # ---------------------------------------------------------------- add: fields that become paths
    "add-gt-sha-path": (lambda c, mp: c.add(edit=_set("sha256.ground_truth", "../../../../escape")),
                        "field 'sha256.ground_truth'"),
    "add-gt-sha-upper": (lambda c, mp: c.add(edit=_set("sha256.ground_truth", "E3" * 32)),
                         "field 'sha256.ground_truth'"),
    "add-ref-path": (lambda c, mp: c.add(edit=_set("protocol.ref", "../../../evaltest@1")), "field 'protocol.ref'"),
    "add-ref-5000-digits": (lambda c, mp: c.add(edit=_set("protocol.ref", HUGE)), "field 'protocol.ref'"),
    "add-ref-newline": (lambda c, mp: c.add(edit=_set("protocol.ref", "evaltest@1\n")), "field 'protocol.ref'"),
    "add-ref-leading-zero": (lambda c, mp: c.add(edit=_set("protocol.ref", "evaltest@01")), "field 'protocol.ref'"),
    "add-frame-sha-not-hex": (lambda c, mp: c.add(edit=_set("frames.0.sha256", "z" * 64)), "field 'frames[0].sha256'"),
    "add-frame-file-escapes": (lambda c, mp: c.add(edit=_set("frames.0.file", "../../../../etc/passwd")),
                               "field 'frames[0].file'"),
    "add-committed-tile-escapes": (lambda c, mp: (_tile(c, "../../../../escape.png"), c.add(*NEW))[1],
                                   "field 'frames[0].tile'"),
    "add-committed-sequence-file-escapes": (lambda c, mp: (_sequence(c, "frames.0.file", "../../../../etc/passwd"),
                                                           c.add(*NEW))[1], "field 'sequence.frames[0].file'"),
    # ---------------------------------------------------------------- add: names
    "add-method-newline": (lambda c, mp: c.add(edit=_set("submission.method", "blur\n")), "field 'submission.method'"),
    "add-method-path": (lambda c, mp: c.add(edit=_set("submission.method", "../blur")), "field 'submission.method'"),
    "add-method-dotdot": (lambda c, mp: c.add(edit=_set("submission.method", "..")), "field 'submission.method'"),
    "add-method-bidi": (lambda c, mp: c.add(*NEW, edit=_set("submission.method", "blur\u202eevil")),
                        "field 'submission.method'"),
    "add-name-newline": (lambda c, mp: c.add("--name", "other\n"), "--name"),
    "add-name-ground-truth": (lambda c, mp: c.add("--name", "ground-truth"), "--name"),
    "add-method-ground-truth": (lambda c, mp: c.add(src="gt-res.json"), "field 'submission.method'"),
    "add-version-isolate": (lambda c, mp: c.add(*NEW, edit=_set("submission.method_version", "1\u2066")),
                            "field 'submission.method_version'"),
    "add-hardware-escape-code": (lambda c, mp: c.add(*NEW, edit=_set("submission.hardware", {"cpu": "Xeon\x1b[2J"})),
                                 "field 'submission.hardware.cpu'"),
    # ---------------------------------------------------------------- add: numbers
    "add-run-times-sum-inf": (lambda c, mp: c.add(*NEW, edit=lambda d: d["submission"]["timings"].update(
        fit_s=1.7e308, render_s=1.7e308)), "field 'submission.timings.fit_s'"),
    "add-run-times-sum-too-big": (lambda c, mp: c.add(*NEW, edit=lambda d: d["submission"]["timings"].update(
        fit_s=9e11, render_s=9e11)), "field 'submission.timings'"),
    # ---------------------------------------------------------------- add: folders not its own
    "add-strip-folder-not-own": (lambda c, mp: (_not_own(c, "other"),
                                                c.add(*NEW, edit=_set("submission.path", str(c.tmp / "gone"))))[1],
                                 "pass --force"),
    "add-frames-link-outside": (lambda c, mp: (_link_outside(c, "frames"), c.add(*NEW))[1], "outside"),
    "add-results-link-outside": (lambda c, mp: (_link_outside(c, "results"), c.add(*NEW))[1], "outside"),
    "add-read-only": (lambda c, mp: (_read_only(c, mp), c.add(*NEW))[1], "not writable"),
    "add-read-only-late": (lambda c, mp: (_read_only_late(c, mp), c.add(*NEW))[1], "cannot write"),
    # ---------------------------------------------------------------- leaderboard: committed inputs
    "page-ref-path": (lambda c, mp: (c.filed(_set("protocol.ref", "../../../../../up@1")), c.page())[1],
                      "field 'protocol.ref'"),
    "page-ref-5000-digits": (lambda c, mp: (c.filed(_set("protocol.ref", HUGE)), c.page())[1], "field 'protocol.ref'"),
    "page-gt-sha-path": (lambda c, mp: (c.filed(_set("sha256.ground_truth", "../../x")), c.page())[1],
                         "field 'sha256.ground_truth'"),
    "page-method-bidi": (lambda c, mp: (c.filed(_set("submission.method", "blur\u202e")), c.page())[1],
                         "field 'submission.method'"),
    "page-method-trailing-newline": (lambda c, mp: (c.filed(_set("submission.method", "blur\n")), c.page())[1],
                                     "field 'submission.method'"),
    "page-hardware-newline": (lambda c, mp: (c.filed(_set("submission.hardware", {"gpu": "A100\n| x |"})), c.page())[1],
                              "field 'submission.hardware.gpu'"),
    "page-interval-note-control": (lambda c, mp: (c.filed(_set("metrics.psnr.interval_note", "few\x07")), c.page())[1],
                                   "field 'metrics.psnr.interval_note'"),
    "page-run-times-sum-inf": (lambda c, mp: (c.filed(lambda d: d["submission"]["timings"].update(
        fit_s=1.7e308, render_s=1.7e308)), c.page())[1], "field 'submission.timings.fit_s'"),
    "page-resamples-huge": (lambda c, mp: (c.filed(_set("statistics.resamples", 10**12)), c.page())[1],
                            "field 'statistics.resamples'"),
    "page-file-name-reserved": (lambda c, mp: (shutil.copy(c.lb / "results" / "blur.json",
                                                           c.lb / "results" / "ground-truth.json"), c.page())[1],
                                "ground-truth.json: file name"),
    "page-tile-escapes": (lambda c, mp: (_tile(c, "../../../../x.png"), c.page())[1], "field 'frames[0].tile'"),
    "page-sequence-file-escapes": (lambda c, mp: (_sequence(c, "frames.0.file", "../../x.png"), c.page())[1],
                                   "field 'sequence.frames[0].file'"),
    "page-sequence-label-bidi": (lambda c, mp: (_sequence(c, "label", "yaw000\u202e"), c.page())[1],
                                 "field 'sequence.label'"),
    "page-sequence-frames-huge": (lambda c, mp: (_sequence(c, "frames", [{"file": f"g/{i}.png", "index": i}
                                                                         for i in range(10_000)]), c.page())[1],
                                  "field 'sequence.frames'"),
    "page-animation-link-outside": (lambda c, mp: (_animation(c, lambda p: p.symlink_to(
        c.parent / "outside" / "keep.txt")), c.page())[1], "leaves"),
    "page-animation-not-webp": (lambda c, mp: (_animation(c, lambda p: p.write_bytes(b"GIF89a" * 10)), c.page())[1],
                                "not a WebP file"),
    "page-animation-truncated": (lambda c, mp: (_animation(c, lambda p: p.write_bytes(
        (c.world / "lb" / p.relative_to(c.lb)).read_bytes()[:80])), c.page())[1], "cannot decode WebP"),
    "page-animation-fifo": (lambda c, mp: (_animation(c, os.mkfifo), c.page())[1], "named pipe"),
    "check-ref-path": (lambda c, mp: (c.filed(_set("protocol.ref", "../../../../../up@1")), c.page("--check"))[1],
                       "field 'protocol.ref'"),
    "page-reported-string-score": (lambda c, mp: (_reported(c, "psnr = 27.79", 'psnr = "27.79"'), c.page())[1],
                                   "field 'rows[0].psnr'"),
    "page-reported-method-newline": (lambda c, mp: (_reported(c, 'method = "MVS"', 'method = "MVS\\n"'), c.page())[1],
                                     "field 'rows[0].method'"),
    "page-reported-decimals-huge": (lambda c, mp: (_reported(c, "decimals = 2", "decimals = 100000000"), c.page())[1],
                                    "field 'decimals'"),
    "page-reported-fifo": (lambda c, mp: ((c.lb / "reported" / "z.toml").unlink(missing_ok=True),
                                          os.mkfifo(c.lb / "reported" / "z.toml"), c.page())[2], "named pipe"),
    "page-plots-link-outside": (lambda c, mp: (_link_outside(c, "plots"), c.page())[1], "outside"),
    "page-read-only": (lambda c, mp: (_read_only(c, mp), c.page())[1], "not writable"),
}


@pytest.mark.parametrize("cid", list(CASES))
def test_hostile_case_exits_2_in_one_line_and_writes_nothing(case, monkeypatch, cid):
    setup, expect = CASES[cid]
    argv = setup(case, monkeypatch)
    inputs = [case.world / n for n in ("ds", "sub", "gt-sub", "lb")]
    before = _snapshot(case.tmp, *inputs)
    before_files = {p: Path(p).read_bytes() for p, (mode, _, _) in before.items() if (mode & 0o170000) == 0o100000}

    def alarm(signum, frame):
        raise TimeoutError(f"{cid}: still running after {SECONDS} s")

    old = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(SECONDS)
    t0 = time.monotonic()
    try:
        rc, out, err = run_cli(*argv, check=None)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    assert rc == 2, f"rc={rc}\nstdout: {out}\nstderr: {err}"
    assert err.count("\n") == 1 and err.endswith("\n") and "Traceback" not in err, err
    assert expect in err, err
    assert len(err) < 1000 and time.monotonic() - t0 < 20, (len(err), time.monotonic() - t0)
    assert _snapshot(case.tmp, *inputs) == before  # nothing written, moved or deleted, in or out of the root
    assert all(Path(p).read_bytes() == data for p, data in before_files.items())


# ---------------------------------------------------------------------------- what must work


ODD = "a|b <script>alert(1)</script> `c` $\\frac{$ & [l](http://x) *e* _f_ ~g~"


def _table_row(md: str, start: str) -> str:
    """The table line whose first cell starts with `start`."""
    return next(ln for ln in md.splitlines() if ln.startswith(f"| {start}"))


def _cells(line: str) -> int:
    """Cells of a Markdown table line: '|' not escaped by a backslash."""
    return len(re.findall(r"(?<!\\)\|", line)) - 1


def test_odd_text_is_escaped_on_both_pages(case):
    # method, version and hardware carry Markdown/HTML markup (all plain text: one line, no
    # controls); filed under a plain --name, then the page is regenerated
    def edit(d):
        d["submission"].update(method=ODD, method_version="<b>1</b>|2", hardware={"cpu": "x|y<i>", "cores": 2})

    run_cli(*case.add("--name", "odd", edit=edit))
    run_cli(*case.page())
    md = (case.lb / "README.md").read_text()
    head = next(ln for ln in md.splitlines() if ln.startswith("| Method |"))
    row = _table_row(md, "a\\|b &lt;script&gt;")
    assert _cells(row) == _cells(head)  # no '|' in a name adds a cell
    for raw in ("<script>", "<b>", "<i>", "[l](http", "`c`", "*e*", "_f_", "~g~"):
        assert raw not in row, raw
    for escaped in ("\\[l\\](http://x)", "\\`c\\`", "&lt;script&gt;", "&lt;b&gt;1&lt;/b&gt;\\|2", "x\\|y&lt;i&gt;"):
        assert escaped in row, escaped
    html = (case.lb / "index.html").read_text()
    assert "<script>alert" not in html and "&lt;script&gt;alert(1)&lt;/script&gt;" in html
    assert (case.lb / "plots").is_dir() and any((case.lb / "plots").glob("*.png"))  # '$' is text, not mathtext
    run_cli(*case.page("--check"))


def test_ground_truth_results_are_filed_under_another_name_cleanly(case):
    run_cli(*case.add("--name", "truth", src="gt-res.json"))
    assert (case.lb / "results" / "truth.json").is_file()
    assert sorted(p.name for p in (case.frames / "truth").iterdir()) == sorted(
        p.name for p in (case.frames / "ground-truth").iterdir())
    run_cli(*case.page())


@pytest.mark.parametrize("mask", [0o022, 0o027])
def test_files_are_created_with_the_umask(case, mask):
    """In a process started with the umask (as a user's shell starts it): a umask is read once
    per process, so changing it inside this one would test nothing real."""
    lb = case.tmp / "fresh"
    shutil.copytree(case.lb / "reported", lb / "reported")
    for argv in (["add", str(case.results()), "--root", str(lb)], ["--root", str(lb)]):
        subprocess.run([sys.executable, "-m", "skyeyes_bench.cli", "leaderboard", *argv], check=True,
                       capture_output=True, preexec_fn=lambda: os.umask(mask), cwd=ROOT, timeout=300)
    made = [p for p in lb.rglob("*") if "reported" not in p.relative_to(lb).parts]
    assert {"index.html", "README.md", "blur.json", "frames.json", "0.png"} <= {p.name for p in made}
    for p in made:
        want = (0o777 if p.is_dir() else 0o666) & ~mask
        assert p.stat().st_mode & 0o777 == want, (p, oct(p.stat().st_mode & 0o777), oct(want))


def test_stale_png_link_is_removed_not_what_it_points_to(case):
    victim = case.parent / "outside" / "victim.png"
    victim.write_bytes(b"not the leaderboard's")
    (case.lb / "plots").mkdir(exist_ok=True)
    (case.lb / "plots" / "old.png").symlink_to(victim)
    run_cli(*case.page())
    assert not (case.lb / "plots" / "old.png").is_symlink()
    assert victim.read_bytes() == b"not the leaderboard's"


def test_force_without_frames_drops_only_its_own_strip_folder(case):
    # `blur` is filed with frames; re-filed with --force from a submission no longer here: its own
    # strip folder goes, the root's sibling named after the method stays
    run_cli(*case.add("--force", edit=_set("submission.path", str(case.tmp / "gone"))))
    assert not (case.frames / "blur").exists() and (case.frames / "ground-truth").is_dir()
    assert (case.parent / "blur" / "keep.txt").read_text() == "not the leaderboard's"
