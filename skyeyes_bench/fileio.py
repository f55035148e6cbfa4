"""File I/O at the edges: the output discipline, atomic writes, JSON, 8-bit sRGB PNG and float32 EXR depth.

Everything that writes goes through a temporary file in the destination folder followed by
`os.replace`, so a crash never leaves a half-written file under the final name. What is
created gets the user's umask (`file_mode`, `folder_mode`), not tempfile's private 0600 / 0700.

The output discipline, the same for every command:

- `check_output`, before any work: an output never is, holds or lies inside an input (with or
  without --force), and --force replaces only an earlier output of the same kind (`OutputKind`).
- `reading(*inputs)`: inside the block, every write of this module checks its destination against
  the inputs once more at the moment of its rename, with symlinks resolved then.
- `output_lock` and `write_unit`: a results file and its sidecars are one unit, written under an
  exclusive lock in an order that a run killed at any point can simply be repeated.
- A full disk (or a read-only folder) while writing is a one-line `UserError`.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import hashlib
import io
import json
import math
import os
import re
import shutil
import stat
import struct
import tempfile
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Iterator

import numpy as np

from .errors import UserError

try:
    import fcntl
except ImportError:  # pragma: no cover  (not POSIX: no advisory locks; runs are not serialised)
    fcntl = None

#: Largest image we agree to decode (pixels). Guards against decompression bombs.
MAX_PIXELS = 8192 * 8192


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


def _cannot_write(path: Path, e: OSError) -> UserError:
    return UserError(f"{path}: cannot write ({e.strerror or _one_line(e)}); nothing was written there")


@contextlib.contextmanager
def _full_disk_is_one_line(path: Path) -> Iterator[None]:
    """Within the block (a caller's writing into a temporary file or folder for `path`), a full
    disk is `_cannot_write`'s one line; any other OSError passes as it is."""
    try:
        yield
    except OSError as e:
        if e.errno in _FULL:
            raise _cannot_write(path, e) from None
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
        raise UserError(f"{out}: cannot resolve the path ({_one_line(e)})") from None
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
    """Inside the block, every write of this module (`atomic_path`, `atomic_dir`, `write_unit`)
    refuses, at the moment of its rename and with symlinks resolved then, a destination that is,
    holds or lies inside one of `inputs` (None entries are ignored): what `check_output` checked
    before the work, checked again at the point of writing."""
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
      a run killed between the renames of `write_unit` leaves: not an output yet, so it is replaced
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
        raise _cannot_write(path, e) from None
    tmp_path = Path(tmp)
    try:
        with _full_disk_is_one_line(path):
            yield tmp_path
        guard(path)
        try:
            os.chmod(tmp_path, file_mode())
            os.replace(tmp_path, path)
        except OSError as e:
            raise _cannot_write(path, e) from None
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
        raise _cannot_write(path, e) from None
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
            raise _cannot_write(path, e) from None
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


# --------------------------------------------------------------------------- one unit: results + sidecars


_HELD: dict[Path, int] = {}  # lock files this process holds -> depth (`output_lock` is re-entrant)


def _lock_file(path: Path) -> Path:
    return path.with_name(f".{path.name}.lock")


@contextlib.contextmanager
def output_lock(path: str | os.PathLike) -> Iterator[None]:
    """Hold the exclusive lock of output `path` for the block: `flock` on `.<name>.lock` beside it,
    removed again on release. A second run that wants the same output while the lock is held gets
    a one-line UserError at once (it never waits). Re-entrant within a process. Parent folders that
    do not exist yet are made, and removed on release while they stay empty (a refused run leaves
    nothing behind). A killed holder's lock ends with its process; its lock file is reused."""
    path = Path(path)
    lock = _lock_file(path)
    key = Path(os.path.abspath(lock))
    if key in _HELD:
        _HELD[key] += 1
        try:
            yield
        finally:
            _HELD[key] -= 1
        return
    made: list[Path] = []
    fd = None
    try:
        for _ in range(50):  # another run may remove the folder or the lock file as we open it
            try:
                made += _make_parents(lock.parent)
                fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0), 0o666)
            except FileNotFoundError:
                continue
            except OSError as e:
                raise UserError(f"{path}: cannot lock it for writing ({lock}: {e.strerror})") from None
            if fcntl is None:
                break
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise UserError(f"{path}: another run is writing it now (lock {lock}); wait for it to end or "
                                "choose another output") from None
            try:
                st = os.stat(lock, follow_symlinks=False)
                if (st.st_dev, st.st_ino) == (os.fstat(fd).st_dev, os.fstat(fd).st_ino):
                    break  # the lock file is still the one on disk: ours
            except FileNotFoundError:
                pass
            os.close(fd)  # the holder before us removed it as we opened it: lock the new one
            fd = None
        else:
            raise UserError(f"{path}: cannot lock it for writing ({lock} keeps changing)")
        _HELD[key] = 1
        try:
            yield
        finally:
            del _HELD[key]
            with contextlib.suppress(OSError):
                os.unlink(lock)  # while still holding it: a waiter that opened it sees it gone
    finally:
        if fd is not None:
            os.close(fd)
        for d in sorted(set(made), key=lambda p: len(p.parts), reverse=True):
            with contextlib.suppress(OSError):
                d.rmdir()  # only while empty: never a folder that received the output


def _make_parents(folder: Path) -> list[Path]:
    """mkdir -p `folder`; the folders this call made, deepest first."""
    made = []
    p = folder
    while not (p.exists() or p.is_symlink()) and p != p.parent:
        made.append(p)
        p = p.parent
    for d in reversed(made):
        with contextlib.suppress(FileExistsError):
            d.mkdir()
    return made


_PARTIAL = ".partial"


def _partials(dest: Path) -> list[Path]:
    """Temporary files `write_unit` makes for `dest` (`.<name>.<8 random characters>.partial`)."""
    pattern = re.compile(rf"^\.{re.escape(dest.name)}\.[a-z0-9_]{{8}}{re.escape(_PARTIAL)}$")
    with contextlib.suppress(OSError):
        return [dest.parent / n for n in os.listdir(dest.parent) if pattern.match(n)]
    return []


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def write_unit(path: str | os.PathLike, data: bytes, sidecars: dict | None = None) -> None:
    """Write the file `path` (bytes `data`) and its `sidecars` ({path: bytes}) as one unit.

    Under `output_lock(path)` (taken here unless this process holds it already):
    1. temporary files a killed run left for these names are removed (no one else holds the lock);
    2. each member is written to a temporary name beside it, flushed to disk, given the umask's mode;
    3. the destinations are checked against `reading`'s inputs, symlinks resolved now;
    4. an existing `path` is removed: from here to step 6 the unit is absent, never mixed;
    5. the sidecars are renamed into place;
    6. `path` is renamed into place last.
    Killed at any step, a run leaves the earlier unit whole, or sidecars without their `path`,
    which `check_output` treats as no output yet: the same run repeated without --force writes
    the same bytes. Any failure, a full disk included, is a one-line UserError that leaves no
    temporary file behind and nothing half-written under a final name.
    """
    path = Path(path)
    members = [*((Path(p), b) for p, b in (sidecars or {}).items()), (path, data)]
    with output_lock(path):
        temps: list[Path] = []
        try:
            for dest, blob in members:
                for old in _partials(dest):
                    old.unlink()
                dest.parent.mkdir(parents=True, exist_ok=True)
                fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=_PARTIAL, dir=dest.parent)
                temps.append(Path(tmp))
                try:
                    _write_all(fd, blob)
                    os.fsync(fd)
                    os.fchmod(fd, file_mode())
                finally:
                    os.close(fd)
            for dest, _ in members:
                guard(dest)
            if path.exists() or path.is_symlink():
                os.unlink(path)
            for (dest, _), tmp in zip(members, temps):
                os.replace(tmp, dest)
        except OSError as e:
            raise _cannot_write(path, e) from None
        finally:
            for tmp in temps:
                with contextlib.suppress(FileNotFoundError):
                    tmp.unlink()


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """What `np.savez(f, **arrays)` writes, as bytes that depend on the arrays alone: stored
    (uncompressed) `.npy` members in the given order with a fixed timestamp (`np.savez` stamps
    the time of writing, so two runs of one computation would differ)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for key, arr in arrays.items():
            member = io.BytesIO()
            np.lib.format.write_array(member, np.asanyarray(arr), allow_pickle=False)
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            zf.writestr(info, member.getvalue(), compress_type=zipfile.ZIP_STORED)
    return buf.getvalue()


def json_bytes(obj: Any) -> bytes:
    """The bytes `write_json` writes for `obj`."""
    return (json.dumps(obj, indent=2, sort_keys=False, allow_nan=True) + "\n").encode()


def write_json(path: str | os.PathLike, obj: Any) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(json_bytes(obj))


#: Largest JSON file read (bytes): far above any manifest or results file, far below memory.
MAX_JSON_BYTES = 256 << 20
#: Deepest nesting of arrays and objects accepted in a JSON file (ours nest 5 deep).
MAX_JSON_DEPTH = 64

_FILE_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a named pipe"), (stat.S_ISSOCK, "a socket"),
               (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"))


def inside(path: str | os.PathLike, root: str | os.PathLike) -> bool:
    """Whether `path`, with every symlink resolved, lies inside `root` (resolved too)."""
    try:
        Path(path).resolve().relative_to(Path(root).resolve())
        return True
    except ValueError:
        return False


def open_regular(path: str | os.PathLike, *, root: str | os.PathLike | None = None) -> BinaryIO:
    """Open a regular file for reading, never blocking: a folder, named pipe, socket or device is
    refused (a named pipe would block a plain open forever); with `root`, the path with its
    symlinks resolved must lie inside `root`. Every refusal is a one-line UserError."""
    path = Path(path)
    if "\x00" in str(path):
        raise UserError(f"{str(path)!r}: path holds a NUL character")
    if root is not None and not inside(path, root):
        raise UserError(f"{path}: leaves {root} (through '..' or a symlink)")
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise UserError(f"{path}: file not found") from None
    except OSError as e:
        raise UserError(f"{path}: cannot open ({e.strerror})") from None
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):
        os.close(fd)
        kind = next((name for test, name in _FILE_KINDS if test(mode)), "not a regular file")
        raise UserError(f"{path}: is {kind}, expected a regular file")
    return os.fdopen(fd, "rb")


def check_regular(path: str | os.PathLike, *, root: str | os.PathLike | None = None) -> Path:
    """`path` if `open_regular` accepts it (for readers that open by name, e.g. image decoders)."""
    with open_regular(path, root=root):
        return Path(path)


def json_problem(obj: Any, allow_nan: bool) -> str | None:
    """Too deep a nesting, or (unless allow_nan) the first non-finite number, with its field."""
    stack: list[tuple[Any, str, int]] = [(obj, "", 1)]
    while stack:
        o, where, depth = stack.pop()
        if depth > MAX_JSON_DEPTH:
            return f"nested more than {MAX_JSON_DEPTH} levels deep (at field '{where}')"
        if isinstance(o, dict):
            items = [(v, f"{where}.{k}" if where else str(k)) for k, v in o.items()]
        elif isinstance(o, list):
            items = [(v, f"{where}[{i}]") for i, v in enumerate(o)]
        else:
            if not allow_nan and isinstance(o, float) and not math.isfinite(o):
                return (f"field '{where}' is {o!r}: JSON numbers are finite (NaN, Infinity and overflowing "
                        f"numbers are refused)")
            continue
        stack.extend((v, w, depth + 1) for v, w in reversed(items))
    return None


def read_json(path: str | os.PathLike, *, root: str | os.PathLike | None = None, allow_nan: bool = False) -> Any:
    """The one JSON reader for files that come from outside: a regular file (see `open_regular`),
    at most MAX_JSON_BYTES, UTF-8, valid JSON, nested at most MAX_JSON_DEPTH deep, numbers that
    fit a float. NaN and Infinity (not JSON, but Python writes them) only with `allow_nan`
    (results files, whose PSNR of a perfect frame is Infinity). Every failure is one UserError line."""
    with open_regular(path, root=root) as f:
        size = os.fstat(f.fileno()).st_size
        if size > MAX_JSON_BYTES:
            raise UserError(f"{path}: {size} bytes, more than the {MAX_JSON_BYTES} a JSON file may hold here")
        data = f.read(MAX_JSON_BYTES + 1)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise UserError(f"{path}: not UTF-8 text (byte {e.start}); expected a JSON file") from None
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as e:
        raise UserError(f"{path}: not valid JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None
    except RecursionError:
        raise UserError(f"{path}: not valid JSON here (nested more than {MAX_JSON_DEPTH} levels deep)") from None
    except ValueError as e:  # an integer of more than 4300 digits
        raise UserError(f"{path}: not valid JSON here ({_one_line(e)})") from None
    if problem := json_problem(obj, allow_nan):
        raise UserError(f"{path}: {problem}")
    return obj


#: The largest TOML file read (protocols, reported numbers): far above any real one.
MAX_TOML_BYTES = 1 << 20


def read_toml(path: str | os.PathLike, what: str) -> dict:
    """A small TOML file, read without blocking (`open_regular`: a named pipe or a device is
    refused), at most `MAX_TOML_BYTES`, UTF-8; every failure is one line naming `path` and saying
    it expected `what` (e.g. "a protocol TOML file")."""
    import tomllib

    path = Path(path)
    try:
        with open_regular(path) as f:
            data = f.read(MAX_TOML_BYTES + 1)
    except OSError as e:
        raise UserError(f"{path}: cannot read {what} ({e.strerror or e})") from None
    if len(data) > MAX_TOML_BYTES:
        raise UserError(f"{path}: more than {MAX_TOML_BYTES} bytes; expected {what}")
    try:
        return tomllib.loads(data.decode("utf-8"))
    except UnicodeDecodeError as e:
        raise UserError(f"{path}: not UTF-8 text (byte {e.start}); expected {what}") from None
    except tomllib.TOMLDecodeError as e:
        raise UserError(f"{path}: not valid TOML ({_one_line(e)})") from None
    except ValueError as e:  # an integer of more than 4300 digits
        raise UserError(f"{path}: not valid TOML here ({_one_line(e)})") from None


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open_regular(path) as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


# --------------------------------------------------------------------------- images


def _oiio():
    import OpenImageIO as oiio  # noqa: N813  (heavy import, kept lazy)

    return oiio


def _one_line(msg: str) -> str:
    """OpenImageIO errors span several lines; user errors are one line."""
    return "; ".join(part.strip() for part in str(msg).splitlines() if part.strip())


def image_header(path: str | os.PathLike) -> tuple[int, int, int, str]:
    """(width, height, channels, pixel format) from the file header, without decoding pixels."""
    oiio = _oiio()
    check_regular(path)  # the decoder opens by name: a named pipe would block it forever
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise UserError(f"{path}: cannot open image ({_one_line(oiio.geterror()) or 'unknown format'})")
    try:
        spec = inp.spec()
        return spec.width, spec.height, spec.nchannels, str(spec.format)
    finally:
        inp.close()


PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}


def png_problem(data: bytes) -> str | None:
    """What is wrong with the bytes of a PNG file, checked before any decoder sees them (libpng
    prints its own lines to stderr on a truncated or corrupt file): every chunk complete with a
    matching CRC up to IEND, an IHDR within the pixel limit, and compressed image data that
    inflates to exactly the rows the header promises (never more: no decompression bomb)."""
    if data[:8] != PNG_MAGIC:
        return "not a PNG file"
    pos, ihdr, idat = 8, None, []
    while True:
        if pos + 12 > len(data):
            return "truncated PNG (the file ends before its IEND chunk)"
        n, typ = struct.unpack(">I4s", data[pos:pos + 8])
        end = pos + 12 + n
        if end > len(data):
            return f"truncated PNG (chunk {typ.decode('latin-1')!r} runs past the end of the file)"
        if zlib.crc32(data[pos + 4:pos + 8 + n]) != struct.unpack(">I", data[end - 4:end])[0]:
            return f"corrupt PNG (chunk {typ.decode('latin-1')!r} fails its CRC)"
        if typ == b"IHDR":
            ihdr = data[pos + 8:pos + 8 + n]
        elif typ == b"IDAT":
            idat.append(data[pos + 8:pos + 8 + n])
        elif typ == b"IEND":
            break
        pos = end
    if ihdr is None or len(ihdr) != 13:
        return "corrupt PNG (no valid IHDR chunk)"
    w, h, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", ihdr)
    if colour not in _PNG_CHANNELS or depth not in (1, 2, 4, 8, 16) or interlace not in (0, 1):
        return f"corrupt PNG (IHDR: bit depth {depth}, colour type {colour}, interlace {interlace})"
    if w == 0 or h == 0 or w * h > MAX_PIXELS:
        return f"image of {w}x{h} outside 1..{MAX_PIXELS} pixels"
    bits = _PNG_CHANNELS[colour] * depth
    if interlace == 0:
        expected = h * (1 + (w * bits + 7) // 8)
    else:  # Adam7: seven passes, each a sub-image with its own filter bytes
        expected = 0
        for x0, y0, dx, dy in ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4),
                               (1, 0, 2, 2), (0, 1, 1, 2)):
            pw, ph = (w - x0 + dx - 1) // dx, (h - y0 + dy - 1) // dy
            if pw and ph:
                expected += ph * (1 + (pw * bits + 7) // 8)
    inflate = zlib.decompressobj()
    try:
        rows = inflate.decompress(b"".join(idat), expected + 1)
    except zlib.error as e:
        return f"corrupt PNG (image data: {e})"
    if len(rows) > expected or inflate.unconsumed_tail:
        return f"corrupt PNG (image data inflates past the {expected} bytes of a {w}x{h} image)"
    if not inflate.eof or len(rows) < expected:
        return f"truncated PNG (image data holds {len(rows)} of the {expected} bytes of a {w}x{h} image)"
    return None


def _read_pixels(path: str | os.PathLike, fmt: str) -> np.ndarray:
    oiio = _oiio()
    with open_regular(path) as f:  # never a named pipe (the decoder opens by name and would block)
        head = f.read(8)
        if head == PNG_MAGIC:
            if problem := png_problem(head + f.read(4 * MAX_PIXELS * 2 + (1 << 20))):
                raise UserError(f"{path}: cannot decode image ({problem})")
    # PNG alpha is unassociated; without this OpenImageIO premultiplies colour by alpha on read,
    # so dropping alpha would leave darkened RGB.
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise UserError(f"{path}: cannot open image ({_one_line(oiio.geterror()) or 'unknown format'})")
    try:
        spec = inp.spec()
        if spec.width * spec.height > MAX_PIXELS:
            raise UserError(
                f"{path}: image of {spec.width}x{spec.height} exceeds the {MAX_PIXELS} pixel limit"
            )
        pixels = inp.read_image(0, 0, 0, spec.nchannels, fmt)
        if pixels is None or (hasattr(pixels, "size") and pixels.size == 0):
            raise UserError(f"{path}: cannot decode image ({_one_line(inp.geterror()) or 'truncated?'})")
        if inp.has_error:
            raise UserError(f"{path}: cannot decode image ({_one_line(inp.geterror())})")
    finally:
        inp.close()
    return np.asarray(pixels).reshape(spec.height, spec.width, spec.nchannels)


def read_image_uint8(path: str | os.PathLike) -> np.ndarray:
    """8-bit image as uint8 [H, W, C] (C as stored)."""
    return _read_pixels(path, "uint8")


def read_image(path: str | os.PathLike) -> np.ndarray:
    """8-bit sRGB image as float32 [H, W, 3] in [0, 1]. Grey is expanded, alpha dropped."""
    px = read_image_uint8(path)
    if px.shape[2] == 1:
        px = np.repeat(px, 3, axis=2)
    elif px.shape[2] == 4:
        px = px[..., :3]
    elif px.shape[2] != 3:
        raise UserError(f"{path}: expected an RGB image, got {px.shape[2]} channels")
    return px.astype(np.float32) / 255.0


def to_uint8(img: np.ndarray) -> np.ndarray:
    """float [0,1] -> uint8 with rounding; uint8 passes through."""
    if img.dtype == np.uint8:
        return img
    return np.clip(np.rint(np.asarray(img, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)


def _write_pixels(path: str | os.PathLike, pixels: np.ndarray, fmt: str, attrs: dict | None = None) -> None:
    oiio = _oiio()
    path = Path(path)
    assert pixels.ndim == 3, pixels.shape  # [H, W, C]: a 2-D array scrambles 1-channel writes
    h, w, c = pixels.shape
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(path))  # format chosen from the final name's extension
        if out is None:
            raise UserError(f"{path}: cannot write this image format ({_one_line(oiio.geterror())})")
        spec = oiio.ImageSpec(w, h, c, fmt)
        for k, v in (attrs or {}).items():
            spec.attribute(k, v)
        if not out.open(str(tmp), spec):
            raise OSError(f"{path}: cannot open for writing: {out.geterror()}")
        ok = out.write_image(np.ascontiguousarray(pixels))
        out.close()
        if not ok:
            raise OSError(f"{path}: write failed: {out.geterror()}")


def write_image(path: str | os.PathLike, img: np.ndarray) -> None:
    """Write an 8-bit PNG from float [0,1] or uint8, [H, W, 3] or [H, W] (grey / labels)."""
    px = to_uint8(img)
    if px.ndim == 2:
        px = px[..., None]
    _write_pixels(path, px, "uint8")


def write_labels(path: str | os.PathLike, labels: np.ndarray) -> None:
    """Write integer labels [H, W] (0..255) as a 1-channel 8-bit PNG."""
    assert labels.ndim == 2, labels.shape
    if labels.min(initial=0) < 0 or labels.max(initial=0) > 255:
        raise ValueError("labels must lie in 0..255")
    _write_pixels(path, labels.astype(np.uint8)[..., None], "uint8")


def read_labels(path: str | os.PathLike) -> np.ndarray:
    return _read_pixels(path, "uint8")[..., 0]


def write_depth(path: str | os.PathLike, depth: np.ndarray) -> None:
    """Write float32 depth [H, W] in metres as a 1-channel EXR (inf allowed for sky)."""
    assert depth.ndim == 2, depth.shape  # [H, W]
    # An empty DateTime keeps OpenImageIO from stamping the write time into the EXR header, so
    # the same depth gives byte-identical files (SynthTown's determinism promise).
    _write_pixels(path, depth.astype(np.float32)[..., None], "float", {"compression": "zip", "DateTime": ""})


def read_depth(path: str | os.PathLike) -> np.ndarray:
    """float32 depth [H, W] in metres from an EXR (first channel)."""
    return _read_pixels(path, "float")[..., 0].astype(np.float32)
