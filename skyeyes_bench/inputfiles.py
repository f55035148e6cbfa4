"""Reading files that come from outside: a regular file opened without blocking (`open_regular`),
the one JSON reader (`read_json`), small TOML files (`read_toml`) and sha256 hashes. Every
refusal is a one-line `UserError`."""

from __future__ import annotations

import hashlib
import json
import math
import os
import stat
from pathlib import Path
from typing import Any, BinaryIO

from .errors import UserError, single_line


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
        raise UserError(f"{path}: not valid JSON here ({single_line(e)})") from None
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
        raise UserError(f"{path}: not valid TOML ({single_line(e)})") from None
    except ValueError as e:  # an integer of more than 4300 digits
        raise UserError(f"{path}: not valid TOML here ({single_line(e)})") from None


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open_regular(path) as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()
