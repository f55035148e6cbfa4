"""One unit: a results file and its sidecars, written under an exclusive lock (`output_lock`,
`write_unit`) in an order that a run killed at any point can simply be repeated; `npz_bytes`, the
sidecar's bytes."""

from __future__ import annotations

import contextlib
import io
import os
import re
import tempfile
import zipfile
from pathlib import Path
from typing import Iterator

import numpy as np

from .errors import UserError
from .outputfiles import cannot_write, file_mode, guard

try:
    import fcntl
except ImportError:  # pragma: no cover  (not POSIX: no advisory locks; runs are not serialised)
    fcntl = None

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
            raise cannot_write(path, e) from None
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
