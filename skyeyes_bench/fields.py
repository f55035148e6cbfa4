"""Checks for the fields of files that come from outside (datasets, captures, submissions,
results). Each takes `where` ("<file>: field 'x.y'"), the value and what was expected, and
returns the value converted or raises a one-line UserError naming all three. Together with
`fileio.read_json` (the one JSON reader) they are the edge: nothing past it sees an unchecked
value.
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np

from .errors import UserError

#: A plain name: a scene, sequence, method, town or lane, and each part of a relative file path.
#: Letters, digits, '_', '.', '-', starting with a letter or digit, so never '', '.', '..', a
#: hidden file, an option, a path separator or a NUL.
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")


def fail(where: str, msg: str):
    raise UserError(f"{where}: {msg}")


def is_number(value: Any) -> bool:
    """A finite JSON number (bool is not a number; NaN and infinities are not finite)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def name(where: str, value: Any, what: str) -> str:
    if not (isinstance(value, str) and NAME.match(value)):
        fail(where, f"expected {what} (a plain name: letters, digits, '_', '.', '-', at most 128, "
                    f"not starting with '.' or '-'), got {value!r}")
    return value


def rel_path(where: str, value: Any, what: str) -> str:
    """A relative POSIX path made of plain names (`ground/000012.png`): it cannot leave its folder."""
    if not (isinstance(value, str) and value and len(value) <= 1024
            and all(NAME.match(part) for part in value.split("/"))):
        fail(where, f"expected {what} (a relative path of plain names such as 'ground/000012.png'), "
                    f"got {value!r}")
    return value


def number(where: str, value: Any, what: str, lo: float = -math.inf, hi: float = math.inf,
           *, lo_open: bool = True) -> float:
    """A finite number with lo < value < hi (lo <= value if not lo_open)."""
    if not (is_number(value) and (lo < value if lo_open else lo <= value) and value < hi):
        fail(where, f"expected {what}, got {value!r}")
    return float(value)


def integer(where: str, value: Any, what: str, lo: int = 0, hi: int | None = None) -> int:
    """An integer lo <= value <= hi (hi: a bound the data imposes, e.g. the number of frames)."""
    if not (isinstance(value, int) and not isinstance(value, bool) and value >= lo
            and (hi is None or value <= hi)):
        rng = f">= {lo}" if hi is None else f"in {lo}..{hi}"
        fail(where, f"expected {what} (an integer {rng}), got {value!r}")
    return int(value)


def numbers(where: str, value: Any, n: int, what: str) -> np.ndarray:
    """A list of exactly n finite numbers, as float64 [n]."""
    if not (isinstance(value, list) and len(value) == n and all(is_number(v) for v in value)):
        fail(where, f"expected {what} ({n} finite numbers), got {_short(value)}")
    return np.asarray(value, dtype=np.float64)


def matrix(where: str, value: Any, rows: int, cols: int, what: str) -> np.ndarray:
    """A rows x cols list of lists of finite numbers, as float64 [rows, cols]."""
    if not (isinstance(value, list) and len(value) == rows and all(
            isinstance(r, list) and len(r) == cols and all(is_number(v) for v in r) for r in value)):
        fail(where, f"expected {what} ({rows}x{cols} finite numbers), got {_short(value)}")
    return np.asarray(value, dtype=np.float64)


def string(where: str, value: Any, what: str, *, pattern: re.Pattern | None = None) -> str:
    if not (isinstance(value, str) and value and (pattern is None or pattern.match(value))):
        fail(where, f"expected {what}, got {_short(value)}")
    return value


def _short(value: Any, limit: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def gaps(indices: list[int], limit: int = 5) -> list[int]:
    """The first `limit` numbers missing from 0..max(indices), in O(len(indices)) time and memory
    whatever the indices' size (an index of 10**12 once made a set of 10**12 numbers)."""
    out: list[int] = []
    expect = 0
    for v in sorted(set(indices)):
        while expect < v and len(out) < limit:
            out.append(expect)
            expect += 1
        if len(out) >= limit:
            break
        expect = v + 1
    return out
