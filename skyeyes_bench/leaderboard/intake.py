"""`skyeyes-bench leaderboard evaluate INBOX/`: a leaderboard's intake. Every submission folder in
INBOX that is new or changed since it was last filed (sha256 of its files) is scored (in turn, or as
shards on Ray: `batch.evaluate_batch`), its results file is filed under the folder's name with
`leaderboard add` (`add.add_result`), and the board is regenerated (`leaderboard.write`).

What it writes: the results of each submission into `--out` (default `INBOX.intake/` beside the
inbox: `<name>.results.json` and its sidecar), the intake's record `--out/intake.json` (per folder:
the sha256 it was scored at and the name it was filed under), and the leaderboard root (through
`add_result` and `write`, whose every path is confined to the root). A submission that cannot be
scored or filed is one line naming it and is skipped; the others are still filed and the board is
regenerated; the exit code is then 2 (1 if one failed for an internal reason).
"""

from __future__ import annotations

import os
from pathlib import Path

from .. import inputfiles, outputfiles, outputunit, safe
from ..errors import UserError, one_line
from ..results import lines_digest
from .tables import ADD_KEY

#: The intake's record in --out, and its format.
STATE_FILE = "intake.json"
STATE_FORMAT = "skyeyes-bench/intake@1"


def submission_sha(folder: Path) -> str:
    """sha256 over every entry below `folder`: its relative path and the sha256 of a regular file
    (a link: its target, never followed; anything else: its kind), so any change of the folder
    changes it."""
    lines = []
    for dirpath, dirnames, filenames in os.walk(folder, followlinks=False):
        for name in filenames + [d for d in dirnames if Path(dirpath, d).is_symlink()]:
            p = Path(dirpath, name)
            rel = p.relative_to(folder).as_posix()
            if p.is_symlink():
                what = f"link {os.readlink(p)}"
            elif p.is_file():  # a regular file (a FIFO or device is not: never opened)
                what = inputfiles.sha256_file(p)
            else:
                what = "not a regular file"
            lines.append(f"{rel} {what}\n")
    return lines_digest(lines)


def _read_state(path: Path) -> dict:
    """The intake's record (empty when there is none yet); a file that is not one is a UserError."""
    if not path.is_file():
        return {"format": STATE_FORMAT, "submissions": {}}
    doc = inputfiles.read_json(path)
    if not (isinstance(doc, dict) and doc.get("format") == STATE_FORMAT and isinstance(doc.get("submissions"), dict)):
        raise UserError(f"{path}: field 'format' is not {STATE_FORMAT!r}: not the record of a leaderboard intake "
                        "(choose another --out)")
    return doc


def _filed_by_us(root: Path, name: str, results: Path) -> bool:
    """Whether `<root>/results/<name>.json` was filed from `results` (an earlier intake of this
    folder: replacing it is ours to do; anything else filed under that name is not)."""
    dest = root / "results" / f"{name}.json"
    if not dest.is_file():
        return False
    try:
        doc = inputfiles.read_json(dest, root=root, allow_nan=True)
    except UserError:
        return False
    added = doc.get(ADD_KEY) if isinstance(doc, dict) else None
    return isinstance(added, dict) and added.get("added_from") == str(results.resolve())


def _folders(inbox: Path) -> list[Path]:
    if not inbox.is_dir():
        raise UserError(f"{inbox}: not a folder (expected an inbox: a folder of submission folders)")
    return sorted(p for p in inbox.iterdir() if p.is_dir() and not p.is_symlink() and not p.name.startswith("."))


def default_out(inbox: Path) -> Path:
    """`INBOX/` -> `INBOX.intake/` beside it (never inside it: that would be another submission)."""
    inbox = Path(inbox).resolve()
    return inbox.with_name(f"{inbox.name}.intake")


def intake(inbox, *, root, out=None, data: str | None = None, ray: str | None = None, shards: int | None = None,
           device: str | None = "cpu", progress: bool = True, allow_missing: bool = False) -> tuple[list[str], int]:
    """Score, file and publish every new or changed submission of `inbox` (module docstring).
    allow_missing: False (the board's rule): a submission whose protocol requires a metric that
    cannot be computed here is one line and skipped, not filed with that metric unavailable.
    Returns (the lines to print, the exit code: 0, or 2 / 1 when a submission was skipped)."""
    from ..batch import combined_exit
    from . import write

    inbox, root = Path(inbox), Path(root)
    out = Path(out) if out is not None else default_out(inbox)
    if not root.is_dir():
        raise UserError(f"{root}: leaderboard folder not found (pass --root DIR)")
    safe.writable(root)
    outputfiles.check_apart(out, inbox, desc="the inbox")
    folders = _folders(inbox)
    with outputunit.output_lock(out / STATE_FILE):  # a second intake into this --out: one line, exit 2
        state = _read_state(out / STATE_FILE)
        lines, todo, codes = _pending(folders, state, root)
        codes += _score_and_file(todo, state, out, root, lines, data=data, ray=ray, shards=shards, device=device,
                                 progress=progress, allow_missing=allow_missing)
    files = write(root)
    lines.append(f"{root}: leaderboard regenerated ({len(files)} files)")
    return lines, combined_exit(codes)


def _pending(folders: list[Path], state: dict, root: Path) -> tuple[list[str], list[tuple[Path, str]], list[int]]:
    """(lines about folders skipped, the (folder, sha256) to score, exit codes of folders refused)."""
    lines, todo, codes = [], [], []
    for f in folders:
        try:
            safe.plain_name(f"{f}", f.name, "a submission folder name (it becomes the name the result is filed under)")
        except UserError as e:
            lines.append(f"{f.name!r}: error: {e}")
            codes.append(e.exit_code)
            continue
        sha = submission_sha(f)
        prev = state["submissions"].get(f.name)
        if isinstance(prev, dict) and prev.get("sha256") == sha and (root / "results" / f"{f.name}.json").is_file():
            lines.append(f"{f.name}: unchanged since it was filed (sha256 {sha[:12]}...): skipped")
            continue
        todo.append((f, sha))
    return lines, todo, codes


def _score_and_file(todo: list[tuple[Path, str]], state: dict, out: Path, root: Path, lines: list[str], *,
                    data, ray, shards, device, progress, allow_missing) -> list[int]:
    """Score `todo` into `out`, file each result under its folder's name and record it in the
    state; a line per folder into `lines`. Returns the exit codes of the folders that failed."""
    from ..batch import Job, evaluate_batch
    from .add import add_result

    jobs = [Job(f, out / f"{f.name}.results.json", data=data) for f, _ in todo]
    codes = []
    for (f, sha), o in zip(todo, evaluate_batch(jobs, ray=ray, shards=shards, device=device, force=True,
                                                progress=progress, allow_missing=allow_missing)):
        if o.error is None:
            try:
                add_result(o.job.out, root=root, name=f.name, force=_filed_by_us(root, f.name, o.job.out))
            except UserError as e:
                o.error, o.exit_code = one_line(e), e.exit_code
        if o.error is not None:
            lines.append(f"{f.name}: error: {o.error}")
            codes.append(o.exit_code)
            continue
        state["submissions"][f.name] = {"sha256": sha, "filed_as": f.name, "results": o.job.out.name}
        outputfiles.write_json(out / STATE_FILE, state)
        lines.append(f"{f.name}: scored ({o.job.out}) and filed as {f.name!r}")
    return codes
