"""Writing outputs: the output discipline, the user's umask, atomic files and folders, JSON.

Everything that writes goes through a temporary file in the destination folder followed by
`os.replace`, so a crash never leaves a half-written file under the final name. What is
created gets the user's umask (`file_mode`, `folder_mode`), not tempfile's private 0600 / 0700.

The output discipline, the same for every command:

- `check_output`, before any work: an output never is, holds or lies inside an input (with or
  without --force), and --force replaces only an earlier output of the same kind (`OutputKind`).
- `reading(*inputs)`: inside the block, every write of this module and of `outputunit` checks its
  destination against the inputs once more at the moment of its rename, with symlinks resolved then.
- `outputunit.output_lock` and `outputunit.write_unit`: a results file and its sidecars are one
  unit, written under an exclusive lock in an order that a run killed at any point can simply be
  repeated.
- A full disk (or a read-only folder) while writing is a one-line `UserError`.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from .errors import UserError, single_line
from .inputfiles import open_regular, read_json


# --------------------------------------------------------------------------- modes


def umask() -> int:
    """The process's umask, read where Linux shows it (/proc/self/status: reading changes
    nothing), else by setting and at once restoring it. Read at each use, so a later
    `os.umask` in the same process is honoured."""
    with contextlib.suppress(OSError, ValueError, IndexError):
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def file_mode() -> int:
    """Mode of a created file: what `open(..., "w")` gives (0o666 less the umask)."""
    return 0o666 & ~umask()


def folder_mode() -> int:
    """Mode of a created folder: what `mkdir` gives (0o777 less the umask)."""
    return 0o777 & ~umask()


#: errno values that say the disk, not the program, failed a write: one line, never a traceback.
_FULL = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG}


def cannot_write(path: Path, e: OSError) -> UserError:
    return UserError(f"{path}: cannot write ({e.strerror or single_line(e)}); nothing was written there")


@contextlib.contextmanager
def _full_disk_is_one_line(path: Path) -> Iterator[None]:
    """Within the block (a caller's writing into a temporary file or folder for `path`), a full
    disk is `cannot_write`'s one line; any other OSError passes as it is."""
    try:
        yield
    except OSError as e:
        if e.errno in _FULL:
            raise cannot_write(path, e) from None
        raise


# --------------------------------------------------------------------------- output discipline


@dataclass(frozen=True)
class OutputKind:
    """What a command writes, so that `--force` replaces an earlier output of the same kind only:
    never a README, a home folder, or another command's output that happens to sit at the path.

    An existing path is an earlier output of this kind when (`recognises`):
    - a folder kind (`folder`): it is an empty folder (nothing to lose), or it holds `marker`, the
      manifest every output of the kind holds at its top (`submission.json`, `dataset.json`);
    - a file kind: it is a regular file (following a symlink) that starts with `magic`, if given;
    - with `formats`, the file (for a folder, its `marker`) is a JSON object whose "format" names one
      of `formats`, or none (a hand-written placeholder such as `{}`; never another command's file).
    """

    what: str  # with its article, e.g. "a results file"
    folder: bool = False
    marker: str | None = None
    formats: tuple[str, ...] = ()
    magic: bytes = b""

    def recognises(self, path: str | os.PathLike) -> bool:
        path = Path(path)
        try:
            if self.folder:
                if not path.is_dir():
                    return False
                if not any(path.iterdir()):
                    return True
                if self.marker is None:
                    return False
                path = path / self.marker
            with open_regular(path) as f:
                if f.read(len(self.magic)) != self.magic:
                    return False
            if self.formats:
                doc = read_json(path, allow_nan=True)
                return isinstance(doc, dict) and doc.get("format", self.formats[0]) in self.formats
            return True
        except (UserError, OSError):
            return False


def _apart(out: Path, inp: Path, desc: str) -> None:
    """Refuse `out` when it is, lies inside or holds `inp` (symlinks resolved as they are now)."""
    try:
        o, i = out.resolve(), inp.resolve()
    except (OSError, RuntimeError) as e:  # a symlink loop
        raise UserError(f"{out}: cannot resolve the path ({single_line(e)})") from None
    if o == i:
        raise UserError(f"{out}: is {desc}; write the output elsewhere")
    if o.is_relative_to(i):
        raise UserError(f"{out}: lies inside {inp} ({desc}); write the output elsewhere")
    if i.is_relative_to(o):
        raise UserError(f"{out}: holds {inp} ({desc}); write the output elsewhere")


def check_apart(out: str | os.PathLike, *inputs: str | os.PathLike | None, desc: str = "an input of this command") -> None:
    """Refuse, in one line, an output folder or file `out` that is, holds or lies inside one of
    `inputs` (None entries ignored; symlinks resolved as they are now)."""
    for inp in inputs:
        if inp is not None:
            _apart(Path(out), Path(inp), desc)


_READING: contextvars.ContextVar[tuple[Path, ...]] = contextvars.ContextVar("skyeyes_reading", default=())


@contextlib.contextmanager
def reading(*inputs: str | os.PathLike | None) -> Iterator[None]:
    """Inside the block, every write of this module and of `outputunit` (`atomic_path`,
    `atomic_dir`, `write_unit`) refuses, at the moment of its rename and with symlinks resolved
    then, a destination that is, holds or lies inside one of `inputs` (None entries are ignored):
    what `check_output` checked before the work, checked again at the point of writing."""
    token = _READING.set(_READING.get() + tuple(Path(p) for p in inputs if p is not None))
    try:
        yield
    finally:
        _READING.reset(token)


def guard(path: str | os.PathLike) -> None:
    """The `reading` check of one destination (a no-op outside a `reading` block)."""
    for inp in _READING.get():
        _apart(Path(path), inp, "an input of this command")


def check_output(path: str | os.PathLike, *, force: bool = False, sidecars=(), outside=(), inputs=(),
                 inputs_are: str = "the inputs", kind: OutputKind | None = None,
                 sidecar_kind: OutputKind | None = None) -> Path:
    """Refuse, before any work and in one line, an output that could not be written or must not be.

    - An output or one of its `sidecars` that is, holds or lies inside one of the `inputs` (files or
      folders; `inputs_are` names them) or one of the existing `outside` folders (e.g. the
      submission being scored), symlinks resolved: refused with or without `force`.
    - A folder where a file is expected; for a folder `kind`, a file.
    - An existing output without `force`; with `force`, one that `kind` does not recognise as an
      earlier output of the same kind (`OutputKind`). A sidecar whose output does not exist is what
      a run killed between the renames of `outputunit.write_unit` leaves: not an output yet, so it is replaced
      without `force` when `sidecar_kind` recognises it.
    - A nearest existing ancestor that is a file or not writable (`creatable`).
    """
    path = Path(path)
    sidecars = tuple(map(Path, sidecars))
    kinds = {path: kind, **{s: sidecar_kind for s in sidecars}}
    inputs = tuple(inputs)
    guarded = [(Path(p), inputs_are if len(inputs) == 1 else f"one of {inputs_are}") for p in inputs]
    guarded += [(Path(r), "an input of this command") for r in outside if Path(r).exists()]
    for p in kinds:
        for inp, desc in guarded:
            _apart(p, inp, desc)
    main_exists = path.exists() or path.is_symlink()
    for p, k in kinds.items():
        if k is not None and k.folder:
            if p.exists() and not p.is_dir():
                raise UserError(f"{p}: is a file; expected a folder (or a path that does not exist)")
        elif p.is_dir():
            raise UserError(f"{p}: is a folder; expected the path of an output file")
        if not (p.exists() or p.is_symlink()):
            continue
        orphan = p != path and not main_exists and k is not None and k.recognises(p)
        if not force and not orphan:
            raise UserError(f"{p}: already exists; pass --force to replace it")
        if k is not None and not k.recognises(p):
            raise _not_same_kind(p, k)
    return creatable(path)


def _not_same_kind(path: Path, kind: OutputKind) -> UserError:
    return UserError(f"{path}: exists and is not {kind.what} (--force replaces only {kind.what} written "
                     "earlier); move it away or choose another path")


def creatable(path: str | os.PathLike) -> Path:
    """`path` if its nearest existing ancestor is a writable folder, else a one-line UserError
    (a parent that is a file used to surface as NotADirectoryError after the work was done)."""
    path = Path(path)
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise UserError(f"{path}: cannot be created ({parent} is a file, not a folder)")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise UserError(f"{path}: cannot be created ({parent} is not writable)")
    return path


# --------------------------------------------------------------------------- atomic writes


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside `path`; on success give it the umask's mode and rename it to
    `path` (checked against `reading`'s inputs first), else delete it. A full disk is one line."""
    path = Path(path)
    suffix = path.suffix if suffix is None else suffix
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp" + suffix, dir=path.parent)
        os.close(fd)
    except OSError as e:
        raise cannot_write(path, e) from None
    tmp_path = Path(tmp)
    try:
        with _full_disk_is_one_line(path):
            yield tmp_path
        guard(path)
        try:
            os.chmod(tmp_path, file_mode())
            os.replace(tmp_path, path)
        except OSError as e:
            raise cannot_write(path, e) from None
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def _existing_folder(path: Path, overwrite: bool, kind: OutputKind | None) -> None:
    if not (path.exists() or path.is_symlink()):
        return
    if not overwrite:
        raise UserError(f"{path}: already exists; pass --force to replace it")
    if not path.is_dir():
        raise UserError(f"{path}: is a file; expected a folder (or a path that does not exist)")
    if kind is not None and not kind.recognises(path):
        raise _not_same_kind(path, kind)


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike, *, overwrite: bool = False, kind: OutputKind | None = None,
               inputs=()) -> Iterator[Path]:
    """Yield a temporary folder beside `path`; on success move it to `path` as a whole.

    `path` may not be, hold or lie inside one of `inputs` (or `reading`'s). An existing `path` is
    refused unless `overwrite`, and then unless `kind` (if given) recognises it as an earlier output
    of the same kind; it is replaced only after the new content is complete. Every check is made
    again at the moment of the move, symlinks resolved then.
    """
    path = Path(path)

    def check() -> None:
        for inp in inputs:
            _apart(path, Path(inp), "an input of this command")
        guard(path)
        _existing_folder(path, overwrite, kind)

    check()
    creatable(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent))
    except OSError as e:
        raise cannot_write(path, e) from None
    try:
        with _full_disk_is_one_line(path):
            yield tmp
        check()
        try:
            os.chmod(tmp, folder_mode())
            if path.exists() or path.is_symlink():
                old = path.with_name(f".{path.name}.old-{os.getpid()}")
                os.replace(path, old)
                os.replace(tmp, path)
                if old.is_symlink():  # the link is replaced, never what it points to
                    old.unlink()
                else:
                    shutil.rmtree(old, ignore_errors=True)
            else:
                os.replace(tmp, path)
        except OSError as e:
            raise cannot_write(path, e) from None
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


class AtomicFolderWriter:
    """Base of the writers that fill a folder all at once (datasets, submissions).

    Inside `with`, `self.root` is a temporary sibling of `final`. On a clean exit after
    `finish()` (which a subclass defines and which must set `self._finished = True`), and once
    `_before_commit()` has raised nothing, the folder is moved to `final`; on an exception, a
    missing `finish()` or a failed check, it is deleted and nothing appears at `final`. A subclass
    sets `kind` so that `overwrite` replaces only an earlier output of that kind; `final` may not be,
    hold or lie inside one of `inputs` (`atomic_dir`).
    """

    kind: OutputKind | None = None

    def __init__(self, final: str | os.PathLike, *, overwrite: bool = False, inputs=()):
        self.final = Path(final)
        self.overwrite = overwrite
        self.inputs = tuple(inputs)
        self._ctx: contextlib.AbstractContextManager[Path] | None = None
        self._finished = False

    def __enter__(self):
        self._ctx = atomic_dir(self.final, overwrite=self.overwrite, kind=self.kind, inputs=self.inputs)
        self.root = self._ctx.__enter__()
        return self

    def _before_commit(self) -> None:
        """Last check of the complete temporary folder; raise to keep it from `final`."""

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            try:
                if not self._finished:
                    raise RuntimeError(f"{type(self).__name__} closed without finish(): nothing was written")
                self._before_commit()
            except BaseException as err:
                self._ctx.__exit__(type(err), err, None)  # deletes the temporary folder
                raise
        return self._ctx.__exit__(exc_type, exc, tb)


# --------------------------------------------------------------------------- JSON


def json_bytes(obj: Any) -> bytes:
    """The bytes `write_json` writes for `obj`."""
    return (json.dumps(obj, indent=2, sort_keys=False, allow_nan=True) + "\n").encode()


def write_json(path: str | os.PathLike, obj: Any) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(json_bytes(obj))
