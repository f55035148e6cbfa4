"""Figures of a measured table: one error-against-run-time plot per metric (with the Pareto
front), and one strip of test frames (rows: ground truth, then each method; columns: the fixed
frames `leaderboard add` saved). Deterministic PNG bytes: fixed metadata, no timestamps."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np

from .. import stats
from .tables import LABEL, Row, Table

#: Strip geometry (pixels): a square tile per frame, a label column on the left, a heading row.
TILE = 128
LABEL_W = 160
HEAD_H = 32
#: Where `leaderboard add` puts the frames and their list (relative to the leaderboard folder).
FRAMES_DIR = "frames"
FRAMES_LIST = "frames.json"
GROUND_TRUTH = "ground-truth"


def _arrow(m: str) -> str:
    return "↑" if stats.higher_is_better(m) else "↓"


def pareto_front(xs: list[float], ys: list[float], higher_is_better: bool) -> list[int]:
    """Indices of the points no other point beats on both run time x (lower is better) and the
    metric y: j dominates i when x_j <= x_i and y_j is at least as good, one of them strictly.
    Sorted by x, then y from best. Pure; O(n^2), n = methods in one table."""
    assert len(xs) == len(ys)
    sign = 1.0 if higher_is_better else -1.0
    g = [sign * y for y in ys]  # larger g is better
    front = [i for i in range(len(xs))
             if not any(xs[j] <= xs[i] and g[j] >= g[i] and (xs[j] < xs[i] or g[j] > g[i]) for j in range(len(xs)))]
    return sorted(front, key=lambda i: (xs[i], -g[i]))


def _plot_rows(t: Table, m: str) -> list[Row]:
    return [r for r in t.rows if r.run_s is not None and r.values.get(m) is not None and math.isfinite(r.values[m])]


def plot_metrics(t: Table) -> list[str]:
    """Metrics of `t` that get a plot (at least one row with a finite value and a run time)."""
    return [m for m in t.metrics if _plot_rows(t, m)]


def plot_name(t: Table, m: str) -> str:
    return f"plots/{t.file_key}-{m}.png"


def render_plot(t: Table, m: str) -> bytes:
    """Metric m (y, with its interval as an error bar) against run time (x, log); the Pareto
    front ringed and connected."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    rows = _plot_rows(t, m)
    xs = [max(r.run_s, 1e-3) for r in rows]
    ys = [float(r.values[m]) for r in rows]
    front = pareto_front(xs, ys, stats.higher_is_better(m))
    # errstate: values near 1e308 (a hand-edited results file) overflow in matplotlib's tick
    # arithmetic; the plot is still drawn, without numpy's warnings on stderr
    with plt.rc_context({"font.size": 8, "figure.dpi": 100, "savefig.dpi": 100}), \
            np.errstate(over="ignore", invalid="ignore"):
        fig, ax = plt.subplots(figsize=(5.0, 3.4))
        for r, x, v in zip(rows, xs, ys):
            lo, hi = r.intervals.get(m, (v, v))
            err = [[max(v - lo, 0.0) if math.isfinite(lo) else 0.0], [max(hi - v, 0.0) if math.isfinite(hi) else 0.0]]
            ax.errorbar([x], [v], yerr=err, fmt="o", capsize=3, ms=4, color="tab:blue")
            # parse_math off: a '$' in a method name is text, not mathtext that may fail to parse
            ax.annotate(r.method, (x, v), textcoords="offset points", xytext=(5, 3), fontsize=7, parse_math=False)
        fx, fy = [xs[i] for i in front], [ys[i] for i in front]
        ax.plot(fx, fy, "-", color="tab:red", lw=1, zorder=3)
        ax.plot(fx, fy, "o", mfc="none", mec="tab:red", ms=10, mew=1.2, zorder=3, label="Pareto front")
        ax.set_xscale("log")
        ax.set_xlim(min(xs) / 3, max(xs) * 3)  # a degenerate range makes log ticks very slow
        ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
        ax.set_xlabel("run time (fit + render), s")
        ax.set_ylabel(f"{LABEL[m]} {_arrow(m)}")
        ax.set_title(f"{t.key}: {LABEL[m]} against run time")
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best", fontsize=7, frameon=False)
        missing = [r.method for r in t.rows if r.run_s is None and r.values.get(m) is not None]
        if missing:
            ax.text(0.01, 0.01, "no run time: " + ", ".join(missing), transform=ax.transAxes, fontsize=6,
                    parse_math=False)
        fig.subplots_adjust(left=0.14, right=0.97, bottom=0.14, top=0.9)  # fixed: tight_layout is slow
        buf = io.BytesIO()
        fig.savefig(buf, format="png", metadata={"Software": None})
        plt.close(fig)
    return buf.getvalue()


# --------------------------------------------------------------------------- strip


def strip_name(t: Table) -> str:
    return f"strips/{t.file_key}.png"


def strip_frames(root: Path, t: Table) -> list[dict] | None:
    """The frames `leaderboard add` chose for t's protocol and dataset (None: none saved yet)."""
    p = Path(root) / FRAMES_DIR / t.frames_key / FRAMES_LIST
    if not p.is_file():
        return None
    from .checks import frames_list

    return frames_list(p)


def strip_rows(root: Path, t: Table) -> list[tuple[str, Path | None]]:
    """(label, frames folder or None when it holds no frames) for ground truth and each row."""
    base = Path(root) / FRAMES_DIR / t.frames_key
    out = []
    for label, sub in [("ground truth", GROUND_TRUTH), *[(r.method, r.name) for r in t.rows]]:
        d = base / sub
        out.append((label, d if d.is_dir() and any(d.glob("*.png")) else None))
    return out


def label_font(size: int = 11):
    """The font of the labels drawn on the strip and the animation (Pillow's default)."""
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: the bitmap font has one size
        return ImageFont.load_default()


def fit_text(draw, text: str, font, width: int) -> str:
    """`text` cut (ending in "…") to fit `width` px in `font`."""
    while text and draw.textlength(text, font=font) > width:
        text = text[:-2] + "…" if len(text) > 2 else ""
    return text


def render_strip(root: Path, t: Table) -> bytes | None:
    """The strip PNG of table t: (1 + rows) x K tiles of TILE px, a label column and a heading
    row; None when no frames were saved for its protocol and dataset."""
    from PIL import Image, ImageDraw

    from .. import imagefiles

    frames = strip_frames(root, t)
    if not frames:
        return None
    rows = strip_rows(root, t)
    k = len(frames)
    img = Image.new("RGB", (LABEL_W + k * TILE, HEAD_H + len(rows) * TILE), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    font = label_font()
    for j, f in enumerate(frames):
        for n, line in enumerate(str(f["label"]).rsplit("/", 1)):  # "scene" / "sequence #index"
            draw.text((LABEL_W + j * TILE + 4, 3 + 14 * n), fit_text(draw, line, font, TILE - 8), fill=(0, 0, 0),
                      font=font)
    for i, (label, folder) in enumerate(rows):
        y = HEAD_H + i * TILE
        draw.text((4, y + TILE // 2 - 6), fit_text(draw, label, font, LABEL_W - 8), fill=(0, 0, 0), font=font)
        for j, f in enumerate(frames):
            x = LABEL_W + j * TILE
            p = folder / f["tile"] if folder is not None else None
            if p is None or not p.is_file():
                draw.rectangle([x + 1, y + 1, x + TILE - 2, y + TILE - 2], fill=(230, 230, 230))
                draw.text((x + 8, y + TILE // 2 - 6), "no frame", fill=(120, 120, 120), font=font)
                continue
            tile = Image.fromarray(imagefiles.to_uint8(imagefiles.read_image(p)))
            scale = min((TILE - 2) / tile.width, (TILE - 2) / tile.height)  # fit the tile; small frames grow
            size = (max(1, round(tile.width * scale)), max(1, round(tile.height * scale)))
            tile = tile.resize(size, Image.Resampling.NEAREST if scale > 1 else Image.Resampling.LANCZOS)
            img.paste(tile, (x + (TILE - tile.width) // 2, y + (TILE - tile.height) // 2))
    buf = io.BytesIO()
    img.save(buf, format="PNG", optimize=False)
    return buf.getvalue()


def save_tile(src: Path, dst: Path, *, root: Path) -> None:
    """Copy frame `src` as a small PNG (longest side at most TILE - 2 px) to `dst` (under `root`),
    atomically, with the user's umask."""
    from PIL import Image

    from .. import imagefiles, safe

    tile = Image.fromarray(imagefiles.to_uint8(imagefiles.read_image(src)))
    tile.thumbnail((TILE - 2, TILE - 2), Image.Resampling.LANCZOS)
    with safe.atomic_file(dst, root=root) as tmp:
        tile.save(tmp, format="PNG")


def frames_list_bytes(frames: list[dict], sequence: dict | None = None) -> bytes:
    """frames.json: the strip frames and (when chosen) the test sequence."""
    doc: dict = {"frames": frames}
    if sequence is not None:
        doc["sequence"] = sequence
    return (json.dumps(doc, indent=2) + "\n").encode()


def write_frames_list(path: Path, frames: list[dict], *, root: Path, sequence: dict | None = None) -> None:
    from .. import safe

    safe.write_bytes(path, frames_list_bytes(frames, sequence), root=root)
