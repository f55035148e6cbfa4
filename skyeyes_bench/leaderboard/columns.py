"""Which columns a measured table shows (issue 58): every column in one order, the core ones the
page shows by default, and those whose value is the same in every row (said once, above the
table, instead of a column that repeats it). Pure: tables in, column lists out; no rendering."""

from __future__ import annotations

from dataclasses import dataclass

from .. import stats
from .tables import LABEL, Table

#: Shown by default on index.html; every other column is behind the "all columns" switch. The
#: paper's metrics and ours that a reader compares first, and what a row costs.
CORE = ("method", "kind", "psnr", "ssim", "lpips", "fid", "fvd", "kvd", "warp", "run", "hardware")
#: Shown even when every row agrees: a row is named by its method, and the page check (and a
#: reader) expects every measured table to say what kind each row is.
KEPT = ("method", "kind")


@dataclass(frozen=True)
class Column:
    key: str  # "method", "kind", "version", a metric name, "run", "hardware" or "peak"
    head: str  # the heading
    core: bool  # shown by default (`CORE`)


def _arrow(m: str) -> str:
    return "↑" if stats.higher_is_better(m) else "↓"


def all_columns(t: Table) -> list[Column]:
    """Every column of measured table `t`, in page order: method, kind, version, the metrics in
    `t.metrics` order, run time, hardware, peak memory."""
    heads = [("method", "Method"), ("kind", "Kind"), ("version", "Version"),
             *[(m, f"{LABEL[m]} {_arrow(m)}") for m in t.metrics],
             ("run", "Run s (fit + render)"), ("hardware", "Hardware"), ("peak", "Peak MB")]
    return [Column(key, head, key in CORE) for key, head in heads]


def _value(t: Table, i: int, key: str):
    """What a cell of column `key` in row `i` shows, as plain data (equal data: equal cells)."""
    r = t.rows[i]
    if key in t.metrics:
        return (r.values.get(key), r.intervals.get(key), r.no_interval.get(key), i in t.best.get(key, []),
                r.seeds.get(key))
    return {"method": lambda: r.method, "kind": lambda: r.kind, "version": lambda: r.version,
            "run": lambda: (r.run_s, r.fit_s, r.render_s), "hardware": lambda: (r.hardware, r.hardware_added),
            "peak": lambda: r.peak_mb}[key]()


def constant(t: Table, key: str) -> bool:
    """Every row of `t` shows the same in column `key` (never for a table of one row: there a
    column says nothing twice)."""
    return len(t.rows) > 1 and all(_value(t, i, key) == _value(t, 0, key) for i in range(1, len(t.rows)))


def choose_columns(t: Table) -> tuple[list[Column], list[Column]]:
    """(the columns to draw, the columns the same in every row): a column the same in every row is
    not drawn (its one value is said above the table), except `KEPT`. Both in `all_columns` order."""
    cols = all_columns(t)
    same = [c for c in cols if c.key not in KEPT and constant(t, c.key)]
    return [c for c in cols if c not in same], same
