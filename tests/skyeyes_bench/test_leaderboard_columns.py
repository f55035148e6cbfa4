"""A board that reads at a glance (issue 58), on hand-built tables (no results files, no browser):
which columns the page shows (`leaderboard.columns`: the core ones by default, a column the same
in every row said once above the table), the current protocol version first
(`tables.current_first`), the legend on one-sided intervals and the page's structure
(`render.render_html`). The page in a browser: test_leaderboard_page.py."""

import re

from skyeyes_bench.leaderboard.columns import CORE, all_columns, choose_columns, constant
from skyeyes_bench.leaderboard.render import BIAS_DOC, legend, one_sided, render_html, render_markdown
from skyeyes_bench.leaderboard.tables import Row, Table, current_first

METRICS = ["psnr", "ssim", "lpips", "fid", "fid_inf", "kid", "fvd", "kvd", "psnr_seen", "warp"]


def _row(method: str, psnr: float, *, version="0.1", hardware="AMD EPYC (2 cores)", fid=(200.0, 180.0, 200.0)):
    """A row with every metric of `METRICS`; FID `(value, lower, upper)`: by default one-sided, as
    the committed rows' are (the upper end is the value)."""
    values = {m: 0.5 for m in METRICS} | {"psnr": psnr, "fid": fid[0]}
    intervals = {m: (0.4, 0.6) for m in METRICS} | {"psnr": (psnr - 1, psnr + 1), "fid": fid[1:]}
    return Row(method=method, version=version, values=values, intervals=intervals, run_s=3.0, fit_s=1.0,
               render_s=2.0, peak_mb=100.0, hardware=hardware, kind="baseline", source=f"{method}.json")


def _table(ref: str, rows: list[Row], key: str = "") -> Table:
    return Table(key or ref, f"{key or ref} — measured", ref, list(METRICS), rows, reported=False, note="n")


def test_core_columns_are_shown_and_the_rest_are_behind_the_switch():
    t = _table("synthtown@4", [_row("a", 16.0, version="0.1"), _row("b", 15.0, version="0.2",
                                                                  hardware="x, NVIDIA H200")])
    cols, same = choose_columns(t)
    # every column the table has, in page order; the metrics as the table orders them
    assert [c.key for c in all_columns(t)] == ["method", "kind", "version", *METRICS, "run", "hardware", "peak"]
    assert [c.key for c in all_columns(t) if c.core] == ["method", "kind", "psnr", "ssim", "lpips", "fid", "fvd",
                                                         "kvd", "warp", "run", "hardware"]
    assert [c.key for c in all_columns(t) if not c.core] == ["version", "fid_inf", "kid", "psnr_seen", "peak"]
    # the metrics that differ between rows: PSNR and nothing else (the rest are 0.5 [0.4, 0.6] in both,
    # FID 200 [180, 200] in both); version and hardware differ, so they stay
    assert [c.key for c in same] == ["ssim", "lpips", "fid", "fid_inf", "kid", "fvd", "kvd", "psnr_seen", "warp",
                                     "run", "peak"]
    assert [(c.key, c.core) for c in cols] == [("method", True), ("kind", True), ("version", False), ("psnr", True),
                                               ("hardware", True)]
    assert set(CORE) <= {c.key for c in all_columns(t)}


def test_a_column_the_same_in_every_row_is_dropped_but_method_and_kind_stay():
    rows = [_row("a", 16.0), _row("b", 15.0, fid=(190.0, 170.0, 190.0))]
    t = _table("synthtown@4", rows)
    cols, same = choose_columns(t)
    keys = [c.key for c in cols]
    assert "version" not in keys and "hardware" not in keys and "peak" not in keys  # "0.1", one machine
    assert {"version", "hardware", "peak", "run"} <= {c.key for c in same}
    assert keys[:2] == ["method", "kind"] and constant(t, "kind")  # both rows "baseline": still shown
    assert keys == ["method", "kind", "psnr", "fid"]
    # a best mark is part of what a cell shows: a tie marked in one row only is not "the same"
    t.best = {"ssim": [0]}
    assert "ssim" in [c.key for c in choose_columns(t)[0]]
    # one row: nothing is said twice, so nothing is dropped
    lone = _table("synthtown@4", rows[:1])
    assert choose_columns(lone)[1] == [] and not constant(lone, "version")


def test_current_protocol_version_first_older_ones_apart():
    tables = [_table(ref, [_row("a", 16.0)], key) for ref, key in [
        ("synthtown@3", "synthtown@3"), ("carla@1", "carla@1"), ("synthtown@10", "synthtown@10"),
        ("synthtown@4", "synthtown@4"), ("synthtown@10", "synthtown@10#2")]]
    current, older = current_first(tables)
    # versions compare as numbers (10 > 4), per protocol id; a second extractor set stays with its version
    assert [t.key for t in current] == ["carla@1", "synthtown@10", "synthtown@10#2"]
    assert [t.key for t in older] == ["synthtown@4", "synthtown@3"]
    assert current_first([]) == ([], [])


def test_legend_names_the_one_sided_columns_and_why():
    t = _table("synthtown@4", [_row("a", 16.0), _row("b", 15.0, fid=(190.0, 170.0, 195.0))])
    assert one_sided(t) == {"fid": "upper"}  # a's FID ends at its value; b's does not
    text, link = legend(t)
    assert text.startswith("One-sided intervals: FID read [lower, value]: these are biased upward with few samples")
    assert link == "why: docs/metrics.md" and BIAS_DOC == "../docs/metrics.md#fid-and-fvd"
    t.rows[0].intervals["kid"] = (0.5, 0.7)  # KID's lower end at its value 0.5
    assert one_sided(t) == {"fid": "upper", "kid": "lower"}
    assert legend(t)[0].startswith("One-sided intervals: FID, KID end at the value: a small-sample bias")
    two = _table("synthtown@4", [_row("a", 16.0, fid=(190.0, 170.0, 195.0))])
    assert one_sided(two) == {} and "none one-sided here" in legend(two)[0]


def test_page_shows_the_current_version_first_with_core_columns_legend_and_sticky_method(tmp_path):
    new = _table("synthtown@4", [_row("a", 16.0), _row("b", 15.0, version="0.2", fid=(190.0, 170.0, 190.0))])
    old = _table("synthtown@3", [_row("a", 14.0), _row("b", 13.0)])
    page = render_html(tmp_path, [old, new], [], [], {})
    first, folded = page.index('data-protocol="synthtown@4"'), page.index('<details class="older">')
    assert first < folded < page.index('data-protocol="synthtown@3"')  # the older version folded, closed
    assert re.search(r'<details class="older"><summary>Older protocol versions: synthtown@3', page)
    section = page[page.index('<section class="board">'):page.index("</section>")]
    # above the table: the legend (linking the reason) and the switch; the same-in-every-row caption
    assert section.index('<p class="legend">One-sided intervals: FID') < section.index('class="allcols"') < \
        section.index("<table")
    assert f'<a href="{BIAS_DOC}">why: docs/metrics.md</a>' in section
    assert "<caption>Same in every row: SSIM 0.500 [0.400, 0.600]; " in section
    assert "Hardware AMD EPYC (2 cores)" in section and "Version" not in section.split("<caption>")[1].split(
        "</caption>")[0]
    heads = re.findall(r"<th( class=\"extra\")?>([^<]*)</th>", section)
    assert [h for extra, h in heads if not extra] == ["Method", "Kind", "PSNR ↑", "FID ↓"]
    assert [h for extra, h in heads if extra] == ["Version"]  # differs between rows: behind the switch
    assert '<td class="extra" data-v="0.2">0.2</td>' in section and "<th>Kind</th>" in section
    assert '<td class="kind" data-v="paper baseline">paper baseline</td>' in section
    # the switch and the sticky column are CSS: no script decides what is shown
    assert ".allcols:not(:checked) ~ .wide .extra { display: none; }" in page
    assert re.search(r"table\.measured td:first-child \{\s*position: sticky; left: 0;[^}]*background: #fff", page)
    # the plots are folded (the strip too, when there is one)
    assert "<details><summary>Plots:" in section or "No plot" in section
    # README.md: the same order, every column, the same legend
    md = render_markdown(tmp_path, [old, new], [], [], {})
    assert md.index("### synthtown@4") < md.index("## Measured on older protocol versions") < \
        md.index("### synthtown@3")
    assert "One-sided intervals: FID read [lower, value]" in md and f"]({BIAS_DOC})" in md
    assert "| Method | Kind | Version | PSNR ↑ | SSIM ↑ |" in md
