"""Tables -> `README.md` and `index.html` text (deterministic: no timestamps)."""

from __future__ import annotations

import html
import math
from pathlib import Path

from .. import stats
from ..metricspec import sample_count_warning
from .columns import Column, all_columns, choose_columns
from .kinds import KINDS, label
from .marks import rules_summary
from .plots import plot_metrics, plot_name, strip_name, strip_rows
from .sequence import FRAME_MS, sequence_name, sequence_rows, table_sequence
from .tables import DIGITS, LABEL, Table, current_first

DAGGER = "†"
#: Marks a hardware cell that `leaderboard add` recorded (the results file did not).
ADDED = "*"

_INTRO = ("Values are `value [lower, upper]`, the interval the results carry (clustered resampling of scenes or "
          "sequences: half-sampling, or the bootstrap in older results) "
          "(`value (too few scenes)` when there are too few scenes for an interval). **Bold**: best in its "
          f"column. {DAGGER}: the best is not credibly better than the runner-up. Credibly better: the "
          "interval of the paired bootstrap of (best − runner-up), signed so that > 0 means better, excludes 0. "
          "With bootstrap replicates in both results files (same resamples of the same scenes) the pairing is "
          "replicate by replicate, for every metric; without them per-frame metrics use a paired bootstrap of "
          "per-sequence differences and set metrics non-overlapping intervals. Each table says which rule "
          "marked each column. Run time = fit + render seconds as the submission reports them. Plots: each "
          "metric against run time (log scale), the Pareto front (methods no other beats on both) ringed and "
          "connected. Strips: the same fixed test frames for every method; under each, one fixed test sequence as "
          "an animation, every method in step with the ground truth, so flicker is seen (docs/leaderboard.md). "
          "Kind: what a row is to the paper (" + "; ".join(f"{lab} = {what}" for lab, what in KINDS.values()) +
          "). Under each table, what each row runs: the parts of its method and, for the diffusion rows, the "
          "training budget.")


#: Characters that Markdown (GitHub's) reads as markup in a table cell or a line of text: HTML
#: (`<`, `>`, `&`), a new cell (`|`), code, emphasis, links and strike-through.
_MD_ESCAPES = {"&": "&amp;", "<": "&lt;", ">": "&gt;", "|": "\\|", "`": "\\`", "\\": "\\\\", "*": "\\*",
               "_": "\\_", "[": "\\[", "]": "\\]", "~": "\\~", "\n": " ", "\r": " "}


def md(text: str) -> str:
    """`text` (from an input: a name, a version, a note) as literal Markdown: every character that
    would be markup escaped, line breaks as spaces (the readers refuse them already), so a cell
    stays one cell and no input adds HTML, links or formatting to README.md."""
    return "".join(_MD_ESCAPES.get(c, c) for c in str(text))


def fmt(m: str, v: float | None, decimals: int | None = None) -> str:
    if v is None:
        return "n/a"
    if math.isinf(v):
        return "∞" if v > 0 else "-∞"
    return f"{v:.{DIGITS[m] if decimals is None else decimals}f}"


def cell_parts(t: Table, i: int, m: str, escape=lambda x: x) -> tuple[str, str, str]:
    """(`value`, `[lower, upper]` or `(why no interval)` or '', and for a run of several seeds
    `mean ± sd` over them or ''), the reason (input text) through `escape`."""
    r = t.rows[i]
    if m in r.intervals:
        lo, hi = r.intervals[m]
        sub = f"[{fmt(m, lo)}, {fmt(m, hi)}]"
    elif m in r.no_interval and r.values.get(m) is not None:
        sub = f"({escape(r.no_interval[m])})"
    else:
        sub = ""
    spread = ""
    if m in r.seeds and r.values.get(m) is not None:
        mean, sd, _ = r.seeds[m]
        spread = f"{fmt(m, mean)} ± {fmt(m, sd) if sd is not None else 'n/a'}"
    return fmt(m, r.values.get(m)), sub, spread


def cell(t: Table, i: int, m: str, escape=lambda x: x) -> str:
    """`value [lower, upper]`, or `value (why no interval)` with the reason (input text) through
    `escape`; for a run of several seeds then `; N seeds: mean ± sd`."""
    value, sub, spread = cell_parts(t, i, m, escape)
    if spread:
        spread = f"{t.rows[i].n_seeds} seeds: {spread}"
        sub = f"{sub}; {spread}" if sub else spread
    return " ".join(p for p in (value, sub) if p)


#: Under a table with a row of several seeds (the page puts the spread on a line of its own).
SEEDS_NOTE = ("A row of several training seeds (reproduce --seeds N) shows its first seed's value and interval; "
              "under them the mean ± sd over its seeds")


def one_sided(t: Table) -> dict[str, str]:
    """Metric -> "upper" / "lower" / "either": the metrics of `t` with a cell whose interval ends at
    its value (`results`: the half-sample draws all fell on one side of the value, so the interval
    was widened to reach it), and which end that is."""
    out: dict[str, str] = {}
    for m in t.metrics:
        for r in t.rows:
            v, iv = r.values.get(m), r.intervals.get(m)
            if v is None or iv is None or iv[0] == iv[1]:
                continue
            end = "upper" if iv[1] == v else "lower" if iv[0] == v else None
            if end:
                out[m] = end if out.get(m, end) == end else "either"
    return out


#: Where the page says why a Fréchet distance's interval can be one-sided (relative to leaderboard/).
BIAS_DOC = "../docs/metrics.md#fid-and-fvd"


def legend(t: Table) -> tuple[str, str]:
    """The one line above a measured table on the intervals, as (text, its closing link's words):
    which columns' intervals end at their value here and why (issue 58: `166.25 [147.26, 166.25]`
    looked like an error)."""
    sides = one_sided(t)
    if not sides:
        return ("Intervals: value [lower, upper], none one-sided here (one is where a set metric's small-sample bias "
                "exceeds its spread)", "docs/metrics.md")
    cols = ", ".join(LABEL[m] for m in t.metrics if m in sides)
    ends = set(sides.values())
    if ends == {"upper"}:  # the Fréchet distances (FID, FVD and their FD∞) on the committed board
        return (f"One-sided intervals: {cols} read [lower, value]: these are biased upward with few samples, so "
                f"every half-sample draw fell below the value", "why: docs/metrics.md")
    where = "above the value" if ends == {"lower"} else "on one side of the value"
    return (f"One-sided intervals: {cols} " + ("read [value, upper]" if ends == {"lower"} else "end at the value") +
            f": a small-sample bias larger than the spread put every half-sample draw {where}", "why: docs/metrics.md")


def num(v) -> str:
    if v is None:
        return "n/a"
    return f"{v:.1f}" if abs(v) >= 10 else f"{v:.2f}"


def run_time(r) -> str:
    if r.run_s is None:
        return "n/a"
    return f"{num(r.run_s)} ({num(r.fit_s)} + {num(r.render_s)})"


def hardware(r, escape=lambda x: x) -> str:
    return escape(r.hardware or "not recorded") + (ADDED if r.hardware_added else "")


def arrow(m: str) -> str:
    return "↑" if stats.higher_is_better(m) else "↓"


def _measured_head(t: Table) -> list[str]:
    return [c.head for c in all_columns(t)]


def same_text(t: Table, c: Column) -> str:
    """What every row of `t` shows in column `c` (one of `choose_columns`'s same-in-every-row) as
    "name value", for the line above the table (a metric without its arrow: nothing to rank)."""
    r = t.rows[0]
    if c.key in t.metrics:
        return f"{LABEL[c.key]} {cell(t, 0, c.key)}"
    return c.head + " " + {"version": lambda: r.version or "not recorded", "run": lambda: run_time(r),
                           "hardware": lambda: hardware(r), "peak": lambda: num(r.peak_mb)}[c.key]()


def _footnotes(t: Table) -> list[str]:
    out = []
    if any(r.hardware_added for r in t.rows):
        out.append(f"{ADDED} hardware recorded by `skyeyes-bench leaderboard add` on the machine that filed the "
                   f"result (its results file did not record the machine that ran it).")
    return out


#: The heading of the per-row list under each measured table (`runs`).
RUNS_HEAD = "What each row runs:"


def runs(t: Table, escape=lambda x: x) -> list[tuple[str, str]]:
    """(method, the rest of its line) per row of `t`, in the table's order, text from inputs through
    `escape`: "(kind label): component; component — training budget". One line per row, not a line
    per budget, so rows that differ in a part (noise, a post-sampling step) are seen to differ."""
    out = []
    for r in t.rows:
        text = f"({label(r.kind)}): " + ("; ".join(r.components) or "components not recorded")
        out.append((escape(r.method), escape(text + (f" — {r.budget}" if r.budget else ""))))
    return out


_NO_STRIP = ("No strip yet: no frames were saved for this protocol and dataset (`leaderboard add` saves them when "
             "the submission and dataset are on the machine).")


def _strip_notes(root: Path, t: Table, files: dict, escape) -> tuple[str | None, str]:
    """(strip path or None, a sentence on rows without frames, its names passed through `escape`)."""
    if strip_name(t) not in files:
        return None, ""
    missing = [escape(label) for label, folder in strip_rows(root, t) if folder is None]
    return strip_name(t), (f"The strip has no frames for: {', '.join(missing)} (submission or dataset not on "
                           f"the machine that added it)." if missing else "")


def _sequence_notes(root: Path, t: Table, files: dict, escape, code) -> tuple[str | None, str]:
    """(composite animation path or None, a sentence naming the sequence and the rows without a
    saved one), text from inputs passed through `escape`, a command through `code`."""
    name = sequence_name(t) if sequence_name(t) in files else None
    missing = [escape(label) for label, p in sequence_rows(root, t) if p is None]
    why = (f"no saved sequence for: {', '.join(missing)} (filed before {code('leaderboard add')} saved one, or the "
           f"submission or dataset was not on the machine that added it)." if missing else "")
    if name is None:
        return None, "No sequence animation yet: " + why if why else ""
    seq = table_sequence(root, t)
    return name, (f"Animation: test sequence {escape(seq['label'])} ({len(seq['frames'])} frames at "
                  f"{1000 / FRAME_MS:g} per second, looping), ground truth first, every row in step. "
                  + (why[0].upper() + why[1:] if why else ""))


def counts_across(measured: list[Table]) -> str:
    """One line when the measured tables scored a set metric on different sample counts ('' if not)."""
    differ = sample_count_warning([(t.key, t.counts) for t in measured])
    return f"Across the tables, {differ}" if differ else ""


def render_markdown(root: Path, measured: list[Table], reported: list[Table], unmeasured: list[str],
                    files: dict) -> str:
    out = ["# Leaderboard", "",
           "Generated by `skyeyes-bench leaderboard` from `leaderboard/results/*.json` (measured, filed with "
           "`skyeyes-bench leaderboard add`) and `leaderboard/reported/*.toml` (numbers printed in papers). Do "
           "not edit by hand; `skyeyes-bench leaderboard --check` fails when this file is stale.", "",
           _INTRO, "", "## Measured", ""]
    if across := counts_across(measured):
        out += [md(across), ""]
    current, older = current_first(measured)
    for t in current + older:
        if older and t is older[0]:
            out += ["## Measured on older protocol versions", "",
                    "Scored with an older version of a protocol above: compare rows within a table, not across "
                    "versions.", ""]
        text, link = legend(t)
        out += [f"### {md(t.title)}", "", md(t.note), "", rules_summary(t), "", f"{text} ([{link}]({BIAS_DOC})).", ""]
        head = _measured_head(t)
        out += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for i, r in enumerate(t.rows):
            cells = [md(r.method), md(label(r.kind)), md(r.version)]
            for m in t.metrics:
                c = cell(t, i, m, md)
                if i in t.best.get(m, []):
                    c = f"**{c}**" + (f" {DAGGER}" if m in t.not_credible else "")
                cells.append(c)
            cells += [run_time(r), hardware(r, md), num(r.peak_mb)]
            out.append("| " + " | ".join(cells) + " |")
        out.append("")
        for f in _footnotes(t):
            out += [f, ""]
        out += [RUNS_HEAD, "", *[f"- **{method}** {text}" for method, text in runs(t, md)], ""]
        plots = [f"![{t.key}: {LABEL[m]} against run time]({plot_name(t, m)})" for m in plot_metrics(t)]
        out += [" ".join(plots) if plots else "No plot: no row records a run time.", ""]
        strip, note = _strip_notes(root, t, files, md)
        if strip:
            out += [f"![{t.key}: the same test frames, ground truth then each method]({strip})", ""]
        else:
            note = _NO_STRIP
        if note:
            out += [note, ""]
        animation, note = _sequence_notes(root, t, files, md, lambda c: f"`{c}`")
        if animation:
            out += [f"![{t.key}: one test sequence, ground truth then each method, in step]({animation})", ""]
        if note:
            out += [note.strip(), ""]
    if unmeasured:
        out += ["No measured rows yet for protocol: " + ", ".join(f"`{p}`" for p in unmeasured) +
                " (any version). File a results file "
                "with `skyeyes-bench leaderboard add RESULTS.json`, then run `skyeyes-bench leaderboard`.", ""]
    out += ["## Reported in papers (not measured here, not ranked with measured rows)", "",
            f"{REPORTED_NOTE} ([What the paper leaves open]({METRICS_DOC}))", ""]
    for t in reported:
        out += [f"### {md(t.title)} ({md(t.protocol)})", "", f"Source: {md(t.citation)}", "", md(t.note), ""]
        head = ["Method", *[f"{LABEL[m]} {arrow(m)}" for m in t.metrics], "Reference"]
        out += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for i, r in enumerate(t.rows):
            cells = [md(r.method)]
            for m in t.metrics:
                c = fmt(m, r.values.get(m), t.decimals)
                cells.append(f"**{c}**" if i in t.best.get(m, []) else c)
            out.append("| " + " | ".join([*cells, md(r.reference)]) + " |")
        out.append("")
    return "\n".join(out).rstrip() + "\n"


#: The one line above the papers' tables (issue 39): why their numbers, PSNR above all, do not
#: read against the measured tables. The link is relative to leaderboard/ (README.md, index.html).
REPORTED_NOTE = ("The paper leaves its metric settings open (clips, resolution, frame set, implementations), and "
                 "its PSNR, 27.8-33.4 dB for every method, cannot be 10 log10(1/MSE) on [0, 1] frames as ours "
                 "(13-17 dB on the measured rows): do not compare these numbers with the measured tables.")
METRICS_DOC = "../docs/metrics.md#what-the-paper-leaves-open"


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
body { font-family: system-ui, sans-serif; margin: 1.5em; color: #222; max-width: 110em; }
table { border-collapse: collapse; margin: 0.3em 0 1em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.5em; text-align: right; white-space: nowrap; }
th { background: #f2f2f2; cursor: pointer; }
td:first-child, th:first-child, td.kind, table.measured th:nth-child(2) { text-align: left; }
td.best { font-weight: bold; }
td small { display: block; font-size: 0.78em; color: #666; font-weight: normal; }
table.measured { font-size: 0.92em; }
table.measured th { white-space: normal; vertical-align: bottom; }
table.measured td.hw { white-space: normal; min-width: 7em; max-width: 12em; text-align: left; }
table.measured td.kind { white-space: normal; min-width: 5em; }
table.measured caption { caption-side: top; text-align: left; color: #555; font-size: 0.9em; padding: 0.2em 0; }
/* the method column stays in view while a wide table scrolls sideways */
table.measured th:first-child, table.measured td:first-child {
  position: sticky; left: 0; z-index: 1; background: #fff; box-shadow: inset -1px 0 #ccc; }
table.measured th:first-child { background: #f2f2f2; }
.allcols:not(:checked) ~ .wide .extra { display: none; }
.allcols + label { font-size: 0.9em; color: #555; cursor: pointer; }
.reported { color: #555; }
.note, .legend { color: #555; font-size: 0.9em; margin: 0.3em 0; }
.legend { color: #333; }
details { margin: 0.4em 0; }
summary { cursor: pointer; color: #333; }
.plots { display: grid; grid-template-columns: repeat(auto-fill, minmax(24em, 1fr)); gap: 0.5em; }
.plots img { width: 100%; }
img.strip { max-width: 100%; }
.wide { overflow-x: auto; }
ul.runs { margin: 0.3em 0; padding-left: 1.4em; }
h3 { margin: 1.2em 0 0.3em; }
"""


def _sort_value(v: float | None) -> str:
    if v is None:
        return ""
    if math.isinf(v):
        return "1e308" if v > 0 else "-1e308"
    return repr(float(v))


def _md_code(text: str) -> str:
    """Markdown `code` -> <code> in escaped text (the intro and notes are shared with README.md)."""
    parts = html.escape(text).split("`")
    return "".join(f"<code>{p}</code>" if i % 2 else p for i, p in enumerate(parts)).replace("**Bold**", "<b>Bold</b>")


def _value_cell(text: str, sub: str = "", v: str = "", cls: str = "", spread: str = "") -> str:
    """A table cell: `text` over `sub` over `spread` in small type (all already escaped), `v` the
    sort key."""
    attr = f' class="{cls}"' if cls else ""
    small = "".join(f"<small>{x}</small>" for x in (sub, spread) if x)
    return f'<td{attr} data-v="{v}">{text}{small}</td>'


def _measured_cell(t: Table, i: int, c: Column) -> str:
    """Row `i`'s cell in column `c` of the page's table (`extra`: hidden until "all columns")."""
    e, r = html.escape, t.rows[i]
    extra = [] if c.core else ["extra"]
    if c.key == "method":
        return _value_cell(e(r.method), f"{r.n_seeds} seeds" if r.n_seeds else "", e(r.method))
    if c.key == "kind":  # its exact form is what the page check and tests look for
        return f'<td class="kind" data-v="{e(label(r.kind))}">{e(label(r.kind))}</td>'
    if c.key in t.metrics:
        best = i in t.best.get(c.key, [])
        value, sub, spread = cell_parts(t, i, c.key, e)
        mark = f" {DAGGER}" if best and c.key in t.not_credible else ""
        return _value_cell(e(value) + mark, sub, _sort_value(r.values.get(c.key)),
                           " ".join(["best"] * best + extra), spread)
    if c.key == "run":
        sub = f"({num(r.fit_s)} + {num(r.render_s)})" if r.run_s is not None else ""
        return _value_cell(num(r.run_s), sub, _sort_value(r.run_s), " ".join(extra))
    if c.key == "hardware":
        return _value_cell(e(hardware(r)), "", e(hardware(r)), " ".join(["hw"] + extra))
    if c.key == "peak":
        return _value_cell(num(r.peak_mb), "", _sort_value(r.peak_mb), " ".join(extra))
    return _value_cell(e(r.version), "", e(r.version), " ".join(extra))  # version


def _measured_table_html(t: Table) -> list[str]:
    """One measured table: the legend line, the "all columns" switch (when some are hidden), the
    table with its same-in-every-row values as the caption. Plain HTML and CSS: the switch is a
    checkbox whose `:checked` state shows the `extra` cells (no script)."""
    e = html.escape
    cols, same = choose_columns(t)
    text, link = legend(t)
    out = [f'<p class="legend">{e(text)} (<a href="{e(BIAS_DOC)}">{e(link)}</a>).</p>']
    if any(r.seeds for r in t.rows):
        out.append(f'<p class="legend">{e(SEEDS_NOTE)}.</p>')
    hidden = [c for c in cols if not c.core]
    if hidden:
        box = f"cols-{t.file_key}"
        out.append(f'<input type="checkbox" class="allcols" id="{e(box)}"><label for="{e(box)}">all columns '
                   f'(+{len(hidden)}: {e(", ".join(c.head for c in hidden))})</label>')
    caption = ("<caption>Same in every row: " + "; ".join(e(same_text(t, c)) for c in same) +
               "</caption>") if same else ""
    out.append(f'<div class="wide"><table class="sortable measured" data-key="{e(t.file_key)}" '
               f'data-protocol="{e(t.protocol)}">{caption}<thead><tr>')
    out.append("".join(f"<th>{e(c.head)}</th>" if c.core else f'<th class="extra">{e(c.head)}</th>' for c in cols)
               + "</tr></thead><tbody>")
    for i in range(len(t.rows)):
        out.append("<tr>" + "".join(_measured_cell(t, i, c) for c in cols) + "</tr>")
    out.append("</tbody></table></div>")
    return out


def _measured_html(root: Path, t: Table, files: dict) -> list[str]:
    """A measured table's section: heading, notes, table, what each row runs, the sequence
    animation; the plots and the strip of test frames folded (they are most of the page's height)."""
    e = html.escape
    out = [f'<section class="board"><h3 id="{e(t.file_key)}">{e(t.title)}</h3>',
           f"<p class=note>{e(t.note)}<br>{e(rules_summary(t))}</p>", *_measured_table_html(t)]
    out += [f"<p class=note>{_md_code(f)}</p>" for f in _footnotes(t)]
    out += [f"<p class=note>{e(RUNS_HEAD)}</p>", f'<ul class="runs note" data-key="{e(t.file_key)}">',
            *[f'<li data-method="{method}"><b>{method}</b> {text}</li>' for method, text in runs(t, e)], "</ul>"]
    animation, note = _sequence_notes(root, t, files, e, lambda c: f"<code>{e(c)}</code>")
    if animation:
        out.append(f'<p><img class="strip sequence" src="{e(animation)}" alt="{e(t.key)}: one test sequence, '
                   f'ground truth then each method, in step"></p>')
    if note:
        out.append(f"<p class=note>{note.strip()}</p>")
    plots = [f'<img src="{e(plot_name(t, m))}" alt="{e(t.key)}: {e(LABEL[m])} against run time">'
             for m in plot_metrics(t)]
    out.append(f'<details><summary>Plots: {len(plots)} metrics against run time (log scale), the Pareto front '
               f'ringed</summary><div class="plots">{"".join(plots)}</div></details>' if plots else
               "<p>No plot: no row records a run time.</p>")
    strip, note = _strip_notes(root, t, files, e)  # names escaped here; the sentence has no markup
    if strip:
        out.append(f'<details><summary>Test frames: the same frames for every method, ground truth first</summary>'
                   f'<p><img class="strip" src="{e(strip)}" alt="{e(t.key)}: the same test frames, ground truth '
                   f'then each method"></p></details>')
    else:
        note = _md_code(_NO_STRIP)
    if note:
        out.append(f"<p class=note>{note}</p>")
    return out + ["</section>"]


def render_html(root: Path, measured: list[Table], reported: list[Table], unmeasured: list[str],
                files: dict) -> str:
    e = html.escape
    out = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
           '<link rel="icon" href="data:,">',  # no favicon request (a 404 would be a console error)
           "<title>skyeyes-bench leaderboard</title>", f"<style>{_CSS}</style></head><body>",
           "<h1>skyeyes-bench leaderboard</h1>",
           "<p class=note>Generated by <code>skyeyes-bench leaderboard</code>; click a column to sort. "
           f"<b>Bold</b>: best in its column; {DAGGER}: not credibly better than the runner-up. "
           "Reported rows are copied from papers and never ranked with measured rows.</p>",
           f"<details><summary>How to read the tables</summary><p class=note>{_md_code(_INTRO)}</p></details>",
           "<h2>Measured</h2>"]
    if across := counts_across(measured):
        out.append(f"<p class=note>{e(across)}</p>")
    current, older = current_first(measured)
    for t in current:
        out += _measured_html(root, t, files)
    if older:
        out.append(f'<details class="older"><summary>Older protocol versions: '
                   f'{e(", ".join(dict.fromkeys(t.protocol for t in older)))} (compare rows within a table, not '
                   f'across versions)</summary>')
        for t in older:
            out += _measured_html(root, t, files)
        out.append("</details>")
    if unmeasured:
        out.append("<p>No measured rows yet for protocol: " + ", ".join(f"<code>{e(p)}</code>" for p in unmeasured) +
                   " (any version). File a results file with "
                   "<code>skyeyes-bench leaderboard add RESULTS.json</code>.</p>")
    out.append("<h2>Reported in papers (not measured here, not ranked with measured rows)</h2>")
    out.append(f'<p class=note>{e(REPORTED_NOTE)} (<a href="{e(METRICS_DOC)}">What the paper leaves open</a>)</p>')
    for t in reported:
        out += [f"<h3 class=reported>{e(t.title)} ({e(t.protocol)})</h3>",
                f"<p class=note>Source: {e(t.citation)}<br>{e(t.note)}</p>",
                '<table class="sortable reported"><thead><tr>']
        head = ["Method", *[f"{LABEL[m]} {arrow(m)}" for m in t.metrics], "Reference"]
        out.append("".join(f"<th>{e(h)}</th>" for h in head) + "</tr></thead><tbody>")
        for i, r in enumerate(t.rows):
            cells = [f'<td data-v="{e(r.method)}">{e(r.method)}</td>']
            for m in t.metrics:
                cls = ' class="best"' if i in t.best.get(m, []) else ""
                v = r.values.get(m)
                cells.append(f'<td{cls} data-v="{_sort_value(v)}">{fmt(m, v, t.decimals)}</td>')
            cells.append(f'<td data-v="{e(r.reference)}">{e(r.reference)}</td>')
            out.append("<tr>" + "".join(cells) + "</tr>")
        out.append("</tbody></table>")
    out += [f"<script>{_JS}</script>", "</body></html>"]
    return "\n".join(out) + "\n"
