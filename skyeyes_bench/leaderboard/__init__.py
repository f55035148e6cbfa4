"""Results -> leaderboard: `leaderboard/README.md`, `index.html`, plots and frame strips.

Inputs (in the leaderboard folder):
  results/*.json     results files of `skyeyes-bench evaluate`, filed by `skyeyes-bench leaderboard
                     add` (measured rows)
  frames/<key>/      small PNGs of fixed test frames per protocol and dataset (`add` saves them):
                     ground-truth/ and one folder per filed name, listed in frames.json
  reported/*.toml    numbers printed in papers (the Skyeyes paper's Tables 1 and 2), marked
                     "reported" and shown in their own tables: never ranked with measured rows.

Measured rows are grouped by protocol id@version, extractor weights and ground truth, so numbers
made with different protocols, extractors or datasets never share a table. Best-in-column marks:
`marks` (paired bootstrap replicates, else the per-sequence / overlap fallback). Outputs:
README.md, index.html, plots/<table>-<metric>.png (error against run time with the Pareto
front) and strips/<table>.png (ground truth and every method on the same frames).

The output is deterministic (no timestamps; fixed PNG metadata), so `--check` can regenerate
and compare.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import UserError
from .add import add_result, choose_frames
from .marks import mark_best
from .plots import pareto_front, render_plot, render_strip, strip_name
from .render import DAGGER, render_html, render_markdown
from .tables import DIGITS as _DIGITS
from .tables import LABEL, METRIC_ORDER, Row, Table, measured_tables, reported_tables, unmeasured_protocols

__all__ = ["METRIC_ORDER", "LABEL", "DAGGER", "Row", "Table", "load_tables", "build", "write", "check",
           "add_result", "choose_frames", "pareto_front", "render_plot", "render_strip", "_DIGITS"]

#: Folders of generated PNGs (stale files in them are removed by `write`, reported by `check`).
GENERATED_DIRS = ("plots", "strips")


def load_tables(root: Path) -> tuple[list[Table], list[Table]]:
    root = Path(root)
    if not root.is_dir():
        raise UserError(f"{root}: leaderboard folder not found")
    measured, reported = measured_tables(root), reported_tables(root)
    for t in measured + reported:
        mark_best(t)
    return measured, reported


def build(root: Path) -> dict[str, bytes]:
    """Every generated file (relative path -> bytes) for the leaderboard folder `root`."""
    from .plots import plot_metrics, plot_name

    root = Path(root)
    measured, reported = load_tables(root)
    files: dict[str, bytes] = {}
    for t in measured:
        for m in plot_metrics(t):
            files[plot_name(t, m)] = render_plot(t, m)
        strip = render_strip(root, t)
        if strip is not None:
            files[strip_name(t)] = strip
    unmeasured = unmeasured_protocols(measured, reported)
    files["README.md"] = render_markdown(root, measured, reported, unmeasured, files).encode()
    files["index.html"] = render_html(root, measured, reported, unmeasured, files).encode()
    return files


def _same_png(a: bytes, b: bytes) -> bool:
    """PNG bytes equal, or (if the encoder differs) the decoded pixels equal."""
    if a == b:
        return True
    import tempfile

    import numpy as np

    from .. import fileio

    with tempfile.TemporaryDirectory() as d:
        pa, pb = Path(d) / "a.png", Path(d) / "b.png"
        pa.write_bytes(a)
        pb.write_bytes(b)
        try:
            return np.array_equal(fileio.read_image_uint8(pa), fileio.read_image_uint8(pb))
        except UserError:
            return False


def _stale_generated(root: Path, files: dict) -> list[Path]:
    return [p for d in GENERATED_DIRS if (root / d).is_dir() for p in sorted((root / d).glob("*.png"))
            if f"{d}/{p.name}" not in files]


def write(root: Path) -> list[str]:
    """Regenerate the leaderboard in place (atomically per file); remove stale plots and strips."""
    from .. import fileio

    root = Path(root)
    files = build(root)
    for rel, data in files.items():
        with fileio.atomic_path(root / rel) as tmp:
            tmp.write_bytes(data)
    for p in _stale_generated(root, files):
        p.unlink()
    return sorted(files)


def check(root: Path) -> list[str]:
    """Files that differ from what the inputs generate (empty: up to date)."""
    root = Path(root)
    files = build(root)
    stale = []
    for rel, data in files.items():
        p = root / rel
        if not p.is_file():
            stale.append(f"{rel} (missing)")
        elif rel.endswith(".png"):
            if not _same_png(p.read_bytes(), data):
                stale.append(f"{rel} (differs)")
        elif p.read_bytes() != data:
            stale.append(f"{rel} (differs)")
    stale += [f"{p.parent.name}/{p.name} (no longer generated)" for p in _stale_generated(root, files)]
    return stale
