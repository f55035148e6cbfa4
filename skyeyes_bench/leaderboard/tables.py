"""Results -> leaderboard: `leaderboard/README.md`, `index.html` and per-protocol plots.

Inputs (in the leaderboard folder):
  results/*.json     results files of `skyeyes-bench evaluate` (measured rows)
  reported/*.toml    numbers printed in papers (the Skyeyes paper's Tables 1 and 2), marked
                     "reported" and shown in their own tables: never ranked with measured rows.

Measured rows are grouped by protocol id@version *and* extractor weights, so numbers made with
different protocols or extractors never share a table. In each table the best value of a
metric is bold; a dagger marks a best that is not credibly better than the runner-up:
per-frame metrics by a paired clustered bootstrap of per-sequence differences (the interval of
the advantage contains 0), set metrics by overlapping bootstrap intervals (conservative: the
features sidecars are not needed).

The output is deterministic (no timestamps; fixed PNG metadata), so `--check` can regenerate
and compare.
"""

from __future__ import annotations

import html
import io
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import fileio, stats
from .errors import UserError
from .metricspec import METRICS

#: Column order, headings and printed decimals: the metric table's (`metricspec`).
METRIC_ORDER = tuple(METRICS)
LABEL = {name: m.label for name, m in METRICS.items()}
_DIGITS = {name: m.decimals for name, m in METRICS.items()}
DAGGER = "†"


@dataclass
class Row:
    method: str
    version: str
    values: dict[str, float | None]  # metric -> value (None: unavailable)
    intervals: dict[str, tuple[float, float]] = field(default_factory=dict)
    sequences: dict[str, dict] = field(default_factory=dict)  # measured: per-sequence values
    run_s: float | None = None  # fit + render seconds
    fit_s: float | None = None
    render_s: float | None = None
    peak_mb: float | None = None
    source: str = ""  # input file name
    reference: str = ""


@dataclass
class Table:
    key: str  # "synthtown@1" (+ "#2" for a second extractor set)
    title: str
    protocol: str
    metrics: list[str]
    rows: list[Row]
    reported: bool
    note: str = ""
    citation: str = ""
    decimals: int | None = None  # reported tables: the precision the paper prints
    gt_sha: str = ""
    best: dict[str, list[int]] = field(default_factory=dict)
    not_credible: set[str] = field(default_factory=set)


# --------------------------------------------------------------------------- inputs


def _measured_tables(root: Path) -> list[Table]:
    from .results import read_results

    groups: dict[tuple, list[tuple[dict, str]]] = {}
    for p in sorted((root / "results").glob("*.json")):
        doc, _ = read_results(p)
        ex = tuple(sorted((k, v.get("weights_sha256")) for k, v in doc.get("extractors", {}).items()
                          if v.get("status") == "ok"))
        key = (doc["protocol"]["ref"], doc["protocol"]["sha256"], ex, doc["sha256"]["ground_truth"])
        groups.setdefault(key, []).append((doc, p.name))
    tables = []
    seen: dict[str, int] = {}
    for (ref, sha, ex, gt), docs in sorted(groups.items(), key=lambda kv: kv[0]):
        seen[ref] = seen.get(ref, 0) + 1
        key = ref if seen[ref] == 1 else f"{ref}#{seen[ref]}"
        rows = []
        metrics = [m for m in METRIC_ORDER if any(m in d["metrics"] for d, _ in docs)]
        for d, name in docs:
            s = d["submission"]
            t = s.get("timings") or {}
            fit, ren = t.get("fit_s"), t.get("render_s")
            rows.append(Row(
                method=str(s.get("method")), version=str(s.get("method_version") or ""),
                values={m: d["metrics"][m]["value"] if d["metrics"].get(m, {}).get("status") == "ok" else None
                        for m in metrics},
                intervals={m: tuple(d["metrics"][m]["interval"]) for m in metrics
                           if d["metrics"].get(m, {}).get("status") == "ok"},
                sequences=d["sequences"], fit_s=fit, render_s=ren,
                run_s=(fit or 0.0) + (ren or 0.0) if fit is not None or ren is not None else None,
                peak_mb=s.get("peak_memory_mb"), source=name))
        rows.sort(key=lambda r: (r.method.lower(), r.version, r.source))
        exs = ", ".join(f"{i} ({(w or '-')[:12]})" for i, w in ex) or "none"
        title = f"{ref} — measured"
        note = (f"protocol sha256 {sha[:12]}…; extractors {exs}; dataset {docs[0][0]['dataset']['name']} "
                f"({len(docs[0][0]['dataset']['sequences'])} sequences, {len(docs[0][0]['frames'])} frames)")
        tables.append(Table(key, title, ref, metrics, rows, reported=False, note=note, gt_sha=gt))
    return tables


def _reported_tables(root: Path) -> list[Table]:
    tables = []
    for p in sorted((root / "reported").glob("*.toml")):
        try:
            raw = tomllib.loads(p.read_text())
        except tomllib.TOMLDecodeError as e:
            raise UserError(f"{p}: not valid TOML ({e})") from None
        for k in ("title", "protocol", "status", "citation", "metrics", "rows"):
            if k not in raw:
                raise UserError(f"{p}: missing key '{k}'")
        if raw["status"] != "reported":
            raise UserError(f"{p}: key 'status' must be \"reported\", got {raw['status']!r}")
        metrics = list(raw["metrics"])  # the paper's column order
        unknown = set(raw["metrics"]) - set(METRIC_ORDER)
        if unknown:
            raise UserError(f"{p}: unknown metrics {sorted(unknown)} (known: {', '.join(METRIC_ORDER)})")
        rows = []
        for i, r in enumerate(raw["rows"]):
            if "method" not in r:
                raise UserError(f"{p}: rows[{i}] has no 'method'")
            rows.append(Row(method=r["method"], version="", values={m: r.get(m) for m in metrics},
                            source=p.name, reference=r.get("reference", "")))
        tables.append(Table(p.stem, raw["title"], raw["protocol"], metrics, rows, reported=True,
                            note=raw.get("note", ""), citation=raw["citation"], decimals=raw.get("decimals")))
    return tables


def _mark_best(t: Table) -> None:
    """Bold the best value per metric; for measured tables, flag a best that is not credibly
    better than the runner-up."""
    from .protocol import load_protocol

    st = None
    for m in t.metrics:
        vals = [(i, r.values.get(m)) for i, r in enumerate(t.rows) if r.values.get(m) is not None]
        if not vals:
            continue
        hib = stats.higher_is_better(m)
        order = sorted(vals, key=lambda iv: -iv[1] if hib else iv[1])
        best_v = order[0][1]
        t.best[m] = [i for i, v in vals if v == best_v]
        if t.reported or len(order) < 2 or len(t.best[m]) > 1:
            continue
        a, b = t.rows[order[0][0]], t.rows[order[1][0]]
        if METRICS[m].kind == "frame":
            st = st or load_protocol(t.protocol).statistics
            seqs = sorted(a.sequences)
            va = np.array([a.sequences[s][m] for s in seqs])
            vb = np.array([b.sequences[s].get(m, math.nan) for s in seqs])
            d = stats.advantage(va, vb, m)
            interval = stats.advantage_interval(d, resamples=st.bootstrap_resamples, level=st.interval, seed=st.seed)
            credible = interval is not None and interval[0] > 0
        else:
            (alo, ahi), (blo, bhi) = a.intervals[m], b.intervals[m]
            credible = ahi < blo if not stats.higher_is_better(m) else alo > bhi
        if not credible:
            t.not_credible.add(m)


def load_tables(root: Path) -> tuple[list[Table], list[Table]]:
    root = Path(root)
    if not root.is_dir():
        raise UserError(f"{root}: leaderboard folder not found")
    measured, reported = _measured_tables(root), _reported_tables(root)
    for t in measured + reported:
        _mark_best(t)
    return measured, reported


# --------------------------------------------------------------------------- rendering


def _fmt(m: str, v: float | None, decimals: int | None = None) -> str:
    if v is None:
        return "n/a"
    if math.isinf(v):
        return "∞" if v > 0 else "-∞"
    return f"{v:.{_DIGITS[m] if decimals is None else decimals}f}"


def _cell(t: Table, i: int, m: str) -> str:
    r = t.rows[i]
    text = _fmt(m, r.values.get(m))
    if m in r.intervals:
        lo, hi = r.intervals[m]
        text += f" [{_fmt(m, lo)}, {_fmt(m, hi)}]"
    return text


def _plot_name(t: Table) -> str:
    return f"plots/{t.key.replace('#', '-')}.png"


def _arrow(m: str) -> str:
    return "↑" if stats.higher_is_better(m) else "↓"


def render_markdown(measured: list[Table], reported: list[Table]) -> str:
    out = ["# Leaderboard", "",
           "Generated by `skyeyes-bench leaderboard` from `leaderboard/results/*.json` (measured) and "
           "`leaderboard/reported/*.toml` (numbers printed in papers). Do not edit by hand; "
           "`skyeyes-bench leaderboard --check` fails when this file is stale.", "",
           f"Values are `value [lower, upper]`, the 95% interval of a clustered bootstrap over sequences. "
           f"**Bold**: best in its column. {DAGGER}: the best is not credibly better than the runner-up "
           f"(paired bootstrap of per-sequence differences for PSNR/SSIM/LPIPS; overlapping intervals for "
           f"FID/KID/FVD/KVD). Run time = fit + render seconds as the submission reports them.", "",
           "## Measured", ""]
    if not measured:
        out += ["No measured results yet. Evaluate a submission with "
                "`skyeyes-bench evaluate SUB --out leaderboard/results/<method>.json`, then run "
                "`skyeyes-bench leaderboard`.", ""]
    for t in measured:
        out += [f"### {t.title}", "", t.note, ""]
        head = ["Method", "Version", *[f"{LABEL[m]} {_arrow(m)}" for m in t.metrics], "Fit s", "Render s",
                "Peak MB"]
        out += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for i, r in enumerate(t.rows):
            cells = [r.method, r.version]
            for m in t.metrics:
                c = _cell(t, i, m)
                if i in t.best.get(m, []):
                    c = f"**{c}**" + (f" {DAGGER}" if m in t.not_credible else "")
                cells.append(c)
            cells += [_num(r.fit_s), _num(r.render_s), _num(r.peak_mb)]
            out.append("| " + " | ".join(cells) + " |")
        out += ["", f"![{t.key}: metrics against run time]({_plot_name(t)})", ""]
    out += ["## Reported in papers (not measured here, not ranked with measured rows)", ""]
    for t in reported:
        out += [f"### {t.title} ({t.protocol})", "", f"Source: {t.citation}", "", t.note, ""]
        head = ["Method", *[f"{LABEL[m]} {_arrow(m)}" for m in t.metrics], "Reference"]
        out += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for i, r in enumerate(t.rows):
            cells = [r.method]
            for m in t.metrics:
                c = _fmt(m, r.values.get(m), t.decimals)
                cells.append(f"**{c}**" if i in t.best.get(m, []) else c)
            out.append("| " + " | ".join([*cells, r.reference]) + " |")
        out.append("")
    return "\n".join(out).rstrip() + "\n"


def _num(v) -> str:
    if v is None:
        return "n/a"
    return f"{v:.1f}" if abs(v) >= 10 else f"{v:.2f}"


_JS = """
document.querySelectorAll('table.sortable th').forEach(function (th) {
  th.addEventListener('click', function () {
    var col = th.cellIndex, body = th.closest('table').tBodies[0], asc = th.dataset.asc !== '1';
    th.closest('tr').querySelectorAll('th').forEach(function (h) { delete h.dataset.asc; });
    th.dataset.asc = asc ? '1' : '0';
    var rows = Array.prototype.slice.call(body.rows);
    rows.sort(function (a, b) {
      var x = a.cells[col].dataset.v, y = b.cells[col].dataset.v, nx = parseFloat(x), ny = parseFloat(y);
      var c = (isNaN(nx) || isNaN(ny)) ? String(x).localeCompare(String(y)) : nx - ny;
      return asc ? c : -c;
    });
    rows.forEach(function (r) { body.appendChild(r); });
  });
});
"""

_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; }
th, td { border: 1px solid #ccc; padding: 0.3em 0.6em; text-align: right; white-space: nowrap; }
th { background: #f2f2f2; cursor: pointer; }
td:first-child, th:first-child { text-align: left; }
td.best { font-weight: bold; }
.reported { color: #555; }
.note { color: #555; font-size: 0.9em; }
"""


def _sort_value(v: float | None) -> str:
    if v is None:
        return ""
    if math.isinf(v):
        return "1e308" if v > 0 else "-1e308"
    return repr(float(v))


def render_html(measured: list[Table], reported: list[Table]) -> str:
    e = html.escape
    out = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
           "<title>skyeyes-bench leaderboard</title>", f"<style>{_CSS}</style></head><body>",
           "<h1>skyeyes-bench leaderboard</h1>",
           f"<p class=note>Generated by <code>skyeyes-bench leaderboard</code>; click a column to sort. Values: "
           f"value [95% clustered-bootstrap interval]. Bold: best; {DAGGER}: not credibly better than the "
           f"runner-up. Reported rows are copied from papers and never ranked with measured rows.</p>",
           "<h2>Measured</h2>"]
    if not measured:
        out.append("<p>No measured results yet.</p>")
    for t in measured:
        out += [f"<h3>{e(t.title)}</h3>", f"<p class=note>{e(t.note)}</p>", '<table class="sortable"><thead><tr>']
        head = ["Method", "Version", *[f"{LABEL[m]} {_arrow(m)}" for m in t.metrics], "Fit s", "Render s", "Peak MB"]
        out.append("".join(f"<th>{e(h)}</th>" for h in head) + "</tr></thead><tbody>")
        for i, r in enumerate(t.rows):
            cells = [f'<td data-v="{e(r.method)}">{e(r.method)}</td>', f'<td data-v="{e(r.version)}">{e(r.version)}</td>']
            for m in t.metrics:
                best = i in t.best.get(m, [])
                mark = f" {DAGGER}" if best and m in t.not_credible else ""
                cls = ' class="best"' if best else ""
                cells.append(f'<td{cls} data-v="{_sort_value(r.values.get(m))}">{e(_cell(t, i, m))}{mark}</td>')
            for v in (r.fit_s, r.render_s, r.peak_mb):
                cells.append(f'<td data-v="{_sort_value(v)}">{_num(v)}</td>')
            out.append("<tr>" + "".join(cells) + "</tr>")
        out += ["</tbody></table>", f'<p><a href="{_plot_name(t)}">plot: metrics against run time</a></p>']
    out.append("<h2>Reported in papers (not measured here, not ranked with measured rows)</h2>")
    for t in reported:
        out += [f"<h3 class=reported>{e(t.title)} ({e(t.protocol)})</h3>",
                f"<p class=note>Source: {e(t.citation)}<br>{e(t.note)}</p>", '<table class="sortable reported"><thead><tr>']
        head = ["Method", *[f"{LABEL[m]} {_arrow(m)}" for m in t.metrics], "Reference"]
        out.append("".join(f"<th>{e(h)}</th>" for h in head) + "</tr></thead><tbody>")
        for i, r in enumerate(t.rows):
            cells = [f'<td data-v="{e(r.method)}">{e(r.method)}</td>']
            for m in t.metrics:
                cls = ' class="best"' if i in t.best.get(m, []) else ""
                cells.append(f'<td{cls} data-v="{_sort_value(r.values.get(m))}">{_fmt(m, r.values.get(m), t.decimals)}</td>')
            cells.append(f'<td data-v="{e(r.reference)}">{e(r.reference)}</td>')
            out.append("<tr>" + "".join(cells) + "</tr>")
        out.append("</tbody></table>")
    out += [f"<script>{_JS}</script>", "</body></html>"]
    return "\n".join(out) + "\n"


def render_plot(t: Table) -> bytes:
    """One PNG per measured table: each metric (with its interval) against run time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker  # noqa: F401

    metrics = [m for m in t.metrics if any(r.values.get(m) is not None and math.isfinite(r.values[m])
                                           for r in t.rows)]
    n = max(1, len(metrics))
    cols = min(n, 4)
    rows = math.ceil(n / cols)
    with plt.rc_context({"font.size": 8, "figure.dpi": 100, "savefig.dpi": 100}):
        fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False)
        for ax, m in zip(axes.flat, metrics):
            for r in t.rows:
                v = r.values.get(m)
                if v is None or not math.isfinite(v):
                    continue
                x = max(r.run_s or 0.0, 1e-3)
                lo, hi = r.intervals.get(m, (v, v))
                err = [[max(v - lo, 0.0)], [max(hi - v, 0.0) if math.isfinite(hi) else 0.0]]
                ax.errorbar([x], [v], yerr=err, fmt="o", capsize=3, ms=4)
                ax.annotate(r.method, (x, v), textcoords="offset points", xytext=(4, 3), fontsize=7)
            ax.set_xscale("log")
            xs = [max(r.run_s or 0.0, 1e-3) for r in t.rows]
            ax.set_xlim(min(xs) / 3, max(xs) * 3)  # a degenerate range makes log ticks very slow
            ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
            ax.set_xlabel("run time (fit + render), s")
            ax.set_title(f"{LABEL[m]} {_arrow(m)}")
            ax.grid(True, alpha=0.3)
        for ax in list(axes.flat)[len(metrics):]:
            ax.axis("off")
        fig.suptitle(f"{t.key}: error against run time")
        # fixed margins: tight_layout doubles the drawing time for no gain here
        fig.subplots_adjust(left=0.08, right=0.98, bottom=0.12 / rows ** 0.5, top=1 - 0.14 / rows ** 0.5,
                            wspace=0.35, hspace=0.7)
        buf = io.BytesIO()
        fig.savefig(buf, format="png", metadata={"Software": None})
        plt.close(fig)
    return buf.getvalue()


def build(root: Path) -> dict[str, bytes]:
    """Every generated file (relative path -> bytes) for the leaderboard folder `root`."""
    measured, reported = load_tables(root)
    files = {"README.md": render_markdown(measured, reported).encode(),
             "index.html": render_html(measured, reported).encode()}
    for t in measured:
        files[_plot_name(t)] = render_plot(t)
    return files


def _same_png(a: bytes, b: bytes) -> bool:
    """PNG bytes equal, or (if the encoder differs) the decoded pixels equal."""
    if a == b:
        return True
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        pa, pb = Path(d) / "a.png", Path(d) / "b.png"
        pa.write_bytes(a)
        pb.write_bytes(b)
        try:
            return np.array_equal(fileio.read_image_uint8(pa), fileio.read_image_uint8(pb))
        except UserError:
            return False


def write(root: Path) -> list[str]:
    """Regenerate the leaderboard in place (atomically per file); remove stale plots."""
    root = Path(root)
    files = build(root)
    for rel, data in files.items():
        with fileio.atomic_path(root / rel) as tmp:
            tmp.write_bytes(data)
    plots = root / "plots"
    if plots.is_dir():
        for p in plots.glob("*.png"):
            if f"plots/{p.name}" not in files:
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
    plots = root / "plots"
    if plots.is_dir():
        stale += [f"plots/{p.name} (no longer generated)" for p in sorted(plots.glob("*.png"))
                  if f"plots/{p.name}" not in files]
    return stale
