"""Checks for the fields of files that come from outside (datasets, captures, submissions,
results). Each takes `where` ("<file>: field 'x.y'"), the value and what was expected, and
returns the value converted or raises a one-line UserError naming all three. Together with
`inputfiles.read_json` (the one JSON reader) they are the edge: nothing past it sees an unchecked
value.
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np

from .errors import UserError, short  # noqa: F401  (fields.short: error values)

#: A plain name: a scene, sequence, method, town or lane, and each part of a relative file path.
#: Letters, digits, '_', '.', '-', starting with a letter or digit, so never '', '.', '..', a
#: hidden file, an option, a path separator or a NUL.
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")


def fail(where: str, msg: str):
    raise UserError(f"{where}: {msg}")


def _expected(where: str, value: Any, expected: str):
    """'missing (expected X)' for an absent field (None), else 'expected X, got V'."""
    if value is None:
        fail(where, f"missing (expected {expected})")
    fail(where, f"expected {expected}, got {short(value)}")


def is_number(value: Any) -> bool:
    """A finite JSON number (bool is not a number; NaN and infinities are not finite)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def name(where: str, value: Any, what: str) -> str:
    if not (isinstance(value, str) and NAME.match(value)):
        _expected(where, value, f"{what} (a plain name: letters, digits, '_', '.', '-', at most 128, "
                                f"not starting with '.' or '-')")
    return value


def rel_path(where: str, value: Any, what: str) -> str:
    """A relative POSIX path made of plain names (`ground/000012.png`): it cannot leave its folder."""
    if not (isinstance(value, str) and value and len(value) <= 1024
            and all(NAME.match(part) for part in value.split("/"))):
        _expected(where, value, f"{what} (a relative path of plain names such as 'ground/000012.png')")
    return value


def number(where: str, value: Any, what: str, lo: float = -math.inf, hi: float = math.inf,
           *, lo_open: bool = True) -> float:
    """A finite number with lo < value < hi (lo <= value if not lo_open)."""
    if not (is_number(value) and (lo < value if lo_open else lo <= value) and value < hi):
        _expected(where, value, what)
    return float(value)


def integer(where: str, value: Any, what: str, lo: int = 0, hi: int | None = None) -> int:
    """An integer lo <= value <= hi (hi: a bound the data imposes, e.g. the number of frames)."""
    if not (isinstance(value, int) and not isinstance(value, bool) and value >= lo
            and (hi is None or value <= hi)):
        rng = f">= {lo}" if hi is None else f"in {lo}..{hi}"
        _expected(where, value, f"{what} (an integer {rng})")
    return int(value)


def numbers(where: str, value: Any, n: int, what: str) -> np.ndarray:
    """A list of exactly n finite numbers, as float64 [n]."""
    if not (isinstance(value, list) and len(value) == n and all(is_number(v) for v in value)):
        _expected(where, value, f"{what} ({n} finite numbers)")
    return np.asarray(value, dtype=np.float64)


def matrix(where: str, value: Any, rows: int, cols: int, what: str) -> np.ndarray:
    """A rows x cols list of lists of finite numbers, as float64 [rows, cols]."""
    if not (isinstance(value, list) and len(value) == rows and all(
            isinstance(r, list) and len(r) == cols and all(is_number(v) for v in r) for r in value)):
        _expected(where, value, f"{what} ({rows}x{cols} finite numbers)")
    return np.asarray(value, dtype=np.float64)


def string(where: str, value: Any, what: str, *, pattern: re.Pattern | None = None) -> str:
    if not (isinstance(value, str) and value and (pattern is None or pattern.match(value))):
        _expected(where, value, what)
    return value





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


class Number:
    """Shape marker for `conform`: any JSON number (results hold inf for a perfect PSNR)."""


class Optional:
    """Shape marker for `conform`: null or the given shape."""

    def __init__(self, shape):
        self.shape = shape


def conform(where: str, value: Any, shape, at: str = "") -> None:
    """Check `value` against `shape` and raise a one-line UserError naming the first field that
    differs. Shapes: a type (str, int, bool, dict, list), `Number`, `Optional(shape)`, a dict of
    required keys -> shapes (other keys allowed; key `str` -> shape: every value), or a
    one-element list [shape] (every item)."""
    def bad(expected: str):
        fail(f"{where}: field '{at or '.'}'", f"expected {expected}, got {short(value)}")

    if isinstance(shape, Optional):
        if value is not None:
            conform(where, value, shape.shape, at)
        return
    if shape is Number:
        if not (isinstance(value, (int, float)) and not isinstance(value, bool)):
            bad("a number")
        return
    if shape is int:
        if not (isinstance(value, int) and not isinstance(value, bool)):
            bad("an integer")
        return
    if isinstance(shape, type):
        if not isinstance(value, shape):
            bad({str: "a string", bool: "true or false", dict: "an object", list: "a list"}.get(shape, shape.__name__))
        return
    if isinstance(shape, list):
        if not isinstance(value, list):
            bad("a list")
        for i, item in enumerate(value):
            conform(where, item, shape[0], f"{at}[{i}]")
        return
    if not isinstance(value, dict):
        bad("an object")
    for key, sub in shape.items():
        if key is str:
            for k, v in value.items():
                conform(where, v, sub, f"{at}.{k}" if at else k)
            continue
        if key not in value:
            fail(f"{where}: field '{f'{at}.{key}' if at else key}'", "missing")
        conform(where, value[key], sub, f"{at}.{key}" if at else key)
