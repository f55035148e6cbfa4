"""Results -> leaderboard: `leaderboard/README.md`, `index.html`, plots, frame strips and
sequence animations.

Inputs (in the leaderboard folder):
  results/*.json     results files of `skyeyes-bench evaluate`, filed by `skyeyes-bench leaderboard
                     add` (measured rows)
  frames/<key>/      small PNGs of fixed test frames per protocol and dataset and an animated WebP
                     of one fixed test sequence (`add` saves them): ground-truth/ and one folder
                     per filed name, the frames and the sequence listed in frames.json
  reported/*.toml    numbers printed in papers (the Skyeyes paper's Tables 1 and 2), marked
                     "reported" and shown in their own tables: never ranked with measured rows.

Measured rows are grouped by protocol id@version, extractor weights and ground truth, so numbers
made with different protocols, extractors or datasets never share a table. Best-in-column marks:
`marks` (paired bootstrap replicates, else the per-sequence / overlap fallback). Outputs:
README.md, index.html, plots/<table>-<metric>.png (error against run time with the Pareto
front), strips/<table>.png (ground truth and every method on the same frames) and
strips/<table>-sequence.webp (ground truth and every method with a saved sequence, in step).

The output is deterministic (no timestamps; fixed PNG metadata; WebP bytes fixed by Pillow and
libwebp), so `--check` can regenerate and compare (`sequence.same_sequence` for another libwebp).
"""

from __future__ import annotations

from pathlib import Path

from ..errors import UserError
from .add import add_result, choose_frames, choose_sequence
from .marks import mark_best
from .plots import pareto_front, render_plot, render_strip, strip_name
from .render import DAGGER, render_html, render_markdown
from .sequence import render_sequence, same_sequence, sequence_name
from .tables import DIGITS as _DIGITS
from .tables import LABEL, METRIC_ORDER, Row, Table, measured_tables, reported_tables, unmeasured_protocols

__all__ = ["METRIC_ORDER", "LABEL", "DAGGER", "Row", "Table", "load_tables", "build", "write", "check",
           "add_result", "choose_frames", "choose_sequence", "pareto_front", "render_plot", "render_strip",
           "render_sequence", "_DIGITS"]

#: Folders of generated images (stale files in them are removed by `write`, reported by `check`).
GENERATED_DIRS = ("plots", "strips")
GENERATED_SUFFIXES = (".png", ".webp")


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
        animation = render_sequence(root, t)
        if animation is not None:
            files[sequence_name(t)] = animation
    unmeasured = unmeasured_protocols(measured, reported)
    files["README.md"] = render_markdown(root, measured, reported, unmeasured, files).encode()
    files["index.html"] = render_html(root, measured, reported, unmeasured, files).encode()
    return files


def _same_png(a: bytes, b: bytes) -> bool:
    """PNG bytes equal, or (if the encoder differs) the decoded pixels equal. Decoded in memory
    (`--check` writes nothing), each checked by `imagefiles.png_problem` before a decoder sees it."""
    if a == b:
        return True
    import io

    import numpy as np
    from PIL import Image

    from .. import imagefiles

    if imagefiles.png_problem(a) or imagefiles.png_problem(b):
        return False
    try:
        pa, pb = (np.asarray(Image.open(io.BytesIO(x)).convert("RGBA")) for x in (a, b))
    except (OSError, ValueError):
        return False
    return pa.shape == pb.shape and np.array_equal(pa, pb)


def _stale_generated(root: Path, files: dict) -> list[Path]:
    """PNG and WebP images (files or links) in plots/ and strips/ that the inputs no longer generate."""
    return [p for d in GENERATED_DIRS if (root / d).is_dir() for p in sorted((root / d).iterdir())
            if p.suffix in GENERATED_SUFFIXES and f"{d}/{p.name}" not in files and (p.is_file() or p.is_symlink())]


def write(root: Path) -> list[str]:
    """Regenerate the leaderboard in place (atomically per file, with the user's umask); remove
    stale plots, strips and animations. Every path written or removed is checked, where it is written or
    removed, to lie under `root` (a planted symlink to elsewhere is refused in one line)."""
    from .. import safe

    root = Path(root)
    if not root.is_dir():
        raise UserError(f"{root}: leaderboard folder not found")
    safe.writable(root)  # before the work: a read-only folder is one line, not a late traceback
    files = build(root)
    for rel in files:  # every target first, so a planted symlink is refused before any file changes
        safe.confined(root / rel, root)
    for rel, data in files.items():
        safe.write_bytes(root / rel, data, root=root)  # and again at the point of writing
    for p in _stale_generated(root, files):
        safe.remove(p, root=root)
    return sorted(files)


def check(root: Path) -> list[str]:
    """Files that differ from what the inputs generate (empty: up to date)."""
    root = Path(root)
    files = build(root)
    from .. import inputfiles

    stale = []
    for rel, data in files.items():
        p = root / rel
        if not p.is_file():
            stale.append(f"{rel} (missing)")
            continue
        with inputfiles.open_regular(p) as f:  # never blocks; a refusal is one line
            on_disk = f.read(inputfiles.MAX_JSON_BYTES)  # far above any page or image generated here
        same = _same_png if rel.endswith(".png") else same_sequence if rel.endswith(".webp") else bytes.__eq__
        if not same(on_disk, data):
            stale.append(f"{rel} (differs)")
    stale += [f"{p.parent.name}/{p.name} (no longer generated)" for p in _stale_generated(root, files)]
    return stale
