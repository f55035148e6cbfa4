"""Values that become file names or page text, and writes kept under one folder (issue 35).

Two halves, both for input that comes from outside (a results file someone files, a TOML of
reported numbers, a committed list of strip frames):

- **Checks where a value is read.** `plain_name` (a value that becomes a file or folder name),
  `plain_text` (a value that becomes page text: no control, line-break or bidirectional/format
  characters, so a name can neither break a table line nor reverse what a reader sees),
  `hex_digest` (a sha256 as lowercase hex of the right length). Each raises a one-line
  `UserError` naming the place, what was expected and what was found, like `fields`.
- **Writes confined to a root, checked at the point of writing.** `confined` resolves a path
  (every symlink and '..' of its folder) and refuses it unless it lies under the root;
  `atomic_file`, `atomic_folder` and `remove` call it immediately before they touch the file
  system, so a path that was fine when parsed but meets a planted symlink is still refused.
  They write through `outputfiles` (the user's umask) and turn an OS refusal (read-only folder,
  full disk) into one line.

`fields.NAME` is matched with `re.match` and a `$` that also matches before a trailing newline;
`plain_name` uses `fullmatch`, so "name\\n" is refused.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import unicodedata
from pathlib import Path
from typing import Any, Iterator

from . import outputfiles
from .errors import UserError, short

#: A plain name (same alphabet as `fields.NAME`), matched whole: no separator, no NUL, no
#: newline, never '', '.', '..', a hidden file or an option.
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,127}")
HEX = re.compile(r"[0-9a-f]+")
#: Unicode categories refused in page text: controls (Cc, newline and tab included), format
#: characters (Cf: the bidirectional embeddings/overrides/isolates U+202A-202E and U+2066-2069,
#: zero-width characters), surrogates, private use, unassigned, and line/paragraph separators.
_NOT_TEXT = frozenset({"Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp"})


def plain_name(where: str, value: Any, what: str) -> str:
    """`value` if it is a plain name usable as one file or folder name, else a one-line UserError."""
    if not (isinstance(value, str) and NAME.fullmatch(value) and ".." not in value):
        raise UserError(f"{where}: expected {what} (a plain name: letters, digits, '_', '.', '-', at most 128, "
                        f"not starting with '.' or '-', no '..'), got {short(value)}")
    return value


def text_problem(value: str, max_len: int) -> str | None:
    """Why `value` is not plain page text (None: it is)."""
    if len(value) > max_len:
        return f"{len(value)} characters, more than {max_len}"
    for i, c in enumerate(value):
        if unicodedata.category(c) in _NOT_TEXT:
            return f"character U+{ord(c):04X} at position {i} (a control, line-break or bidirectional/format character)"
    return None


def plain_text(where: str, value: Any, what: str, *, max_len: int = 200, empty: bool = True) -> str:
    """`value` if it is a string fit to print on a page (see `text_problem`), else a one-line UserError."""
    problem = ("not a string" if not isinstance(value, str) else
               "empty" if not value and not empty else text_problem(value, max_len))
    if problem:
        raise UserError(f"{where}: expected {what} (one line of plain text, at most {max_len} characters, no "
                        f"control or bidirectional characters), got {short(value)}: {problem}")
    return value


def hex_digest(where: str, value: Any, what: str = "a sha256", n: int = 64) -> str:
    """`value` if it is `n` lowercase hex digits, else a one-line UserError."""
    if not (isinstance(value, str) and len(value) == n and HEX.fullmatch(value)):
        raise UserError(f"{where}: expected {what} ({n} lowercase hex digits), got {short(value)}")
    return value


# --------------------------------------------------------------------------- confined writes


def confined(path: str | os.PathLike, root: str | os.PathLike) -> Path:
    """`path` with its folder resolved (symlinks, '..'), if that lies under `root` (resolved too)
    and is not `root` itself; else a one-line UserError. The last component is kept as it is:
    replacing or unlinking it acts on the link itself, never on what a link points to."""
    path = Path(path)
    if path.name in ("", ".", ".."):
        raise UserError(f"{path}: not a file name under {root}; refused to write or delete it")
    base = Path(root).resolve()
    target = path.parent.resolve() / path.name
    if target == base or not target.is_relative_to(base):
        raise UserError(f"{path}: resolves to {target}, outside {root} (through '..' or a symlink); refused to "
                        f"write or delete it")
    return target


def writable(root: str | os.PathLike) -> Path:
    """`root` if it is a folder this process may create files in, else a one-line UserError (before
    any work is done; `atomic_file` still turns a refusal at write time into one line)."""
    root = Path(root)
    if not root.is_dir():
        raise UserError(f"{root}: folder not found")
    if not os.access(root, os.W_OK | os.X_OK):
        raise UserError(f"{root}: not writable (read-only folder or file system); nothing was written")
    return root


def _os_refusal(path: Path, err: OSError) -> UserError | None:
    """One line for an OS refusal to write (permission, read-only, full disk, ...); None for an
    OSError that is not one (e.g. an image library's decode error, which has no errno)."""
    if err.errno is None:
        return None
    return UserError(f"{path}: cannot write ({err.strerror or err}); check that the folder is writable and the "
                     f"disk has room")


@contextlib.contextmanager
def _confined_write(writer, path: str | os.PathLike, root: str | os.PathLike, **kw) -> Iterator[Path]:
    """`writer` (`outputfiles.atomic_path` or `atomic_dir`) of `path`, which must lie under `root`
    (checked here, at the point of writing); an OS refusal is one line."""
    target = confined(path, root)
    try:
        with writer(target, **kw) as tmp:  # the umask's mode, at the rename
            yield tmp
    except OSError as e:
        if (err := _os_refusal(Path(path), e)) is None:
            raise
        raise err from None


def atomic_file(path: str | os.PathLike, *, root: str | os.PathLike, suffix: str | None = None):
    """`outputfiles.atomic_path` for a file that must lie under `root` (`_confined_write`)."""
    return _confined_write(outputfiles.atomic_path, path, root, suffix=suffix)


def write_bytes(path: str | os.PathLike, data: bytes, *, root: str | os.PathLike) -> Path:
    with atomic_file(path, root=root) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_folder(path: str | os.PathLike, *, root: str | os.PathLike, overwrite: bool = False):
    """`outputfiles.atomic_dir` for a folder that must lie under `root` (`_confined_write`)."""
    return _confined_write(outputfiles.atomic_dir, path, root, overwrite=overwrite)


def remove(path: str | os.PathLike, *, root: str | os.PathLike) -> None:
    """Delete a file, a link or a folder tree that lies under `root` (checked here, at the point of
    deleting); a link is unlinked, never followed. Absent: nothing to do."""
    target = confined(path, root)
    try:
        if target.is_symlink() or (target.exists() and not target.is_dir()):
            target.unlink()
        elif target.is_dir():
            shutil.rmtree(target)
    except OSError as e:
        raise UserError(f"{path}: cannot delete ({e.strerror or e})") from None
