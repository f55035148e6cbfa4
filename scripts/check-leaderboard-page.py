#!/usr/bin/env python3
"""Open the leaderboard page in headless Chromium and check what a reader would see.

    .venv/bin/python scripts/check-leaderboard-page.py [PAGE] [--screenshot PNG] [--expect-measured]
                                                       [--expect-animation]

PAGE defaults to leaderboard/index.html of this checkout. Checks: the page loads with no console
error (a missing image is one: "Failed to load resource"), every <img> decoded (naturalWidth >
0), every sequence animation (`<img class="sequence">`) is an animated WebP of more than one
frame (its file, opened with Pillow) and decoded in the browser, at least one table with rows (and
a measured table with --expect-measured, a sequence animation with --expect-animation), every
measured table has a Kind column with a value in every row and a "What each row runs" list that
names every row of its table, and a click on a column heading sorts without an error. At a
1400 px wide viewport (issue 58, a board that reads at a glance): the first table on the page is
a measured table of the current protocol version (the highest of its protocol id on the page),
tables of older versions are folded away, and every shown measured table has a legend line above
it on one-sided intervals (linking docs/metrics.md), fits the viewport with its default columns
(no sideways scrolling), shows its hidden columns behind an "all columns" switch, and keeps its
method column in view (sticky) while it scrolls sideways with all columns shown. Writes a
full-page screenshot (default: a temporary file; never commit it) and prints its path.

Needs Debian's `chromium` and `chromium-driver` and the `selenium` package (the `dev` extra).
When one is missing: exit 1 if CI=true (CI must run the check), else say so and exit 0.
Exit codes: 0 passed (or skipped outside CI), 1 failed.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CHROMIUM = ("chromium", "chromium-browser", "google-chrome")
DRIVER = "chromedriver"
#: The viewport the page is checked at (a laptop's browser window).
WIDTH, HEIGHT = 1400, 1000


def _missing() -> str | None:
    """What is missing to run the check, or None."""
    if not any(shutil.which(c) for c in CHROMIUM):
        return "Chromium not found (apt-get install -y chromium chromium-driver)"
    if not shutil.which(DRIVER):
        return "chromedriver not found (apt-get install -y chromium-driver)"
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium not installed (pip install -e '.[dev]')"
    return None


def _driver(width: int, height: int):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = next(shutil.which(c) for c in CHROMIUM if shutil.which(c))
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
              f"--window-size={width},{height}", "--hide-scrollbars"):
        opts.add_argument(a)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(options=opts, service=Service(shutil.which(DRIVER)))


def animation_problem(page: Path, src: str) -> str | None:
    """Why the image `src` (relative to `page`) is not an animation of several frames (None: it is
    one). Pillow reads the file: a browser decodes a still image just as well."""
    from urllib.parse import unquote, urlsplit

    from PIL import Image, UnidentifiedImageError

    parts = urlsplit(src)
    path = (page.parent / unquote(parts.path)).resolve()
    if parts.scheme or parts.netloc or not path.is_relative_to(page.parent.resolve()):
        return f"{page}: animation {src} is not a file beside the page"
    try:
        with Image.open(path) as im:
            fmt, frames = im.format, getattr(im, "n_frames", 1)
    except (OSError, UnidentifiedImageError) as e:
        return f"{page}: animation {src} cannot be read ({e})"
    if fmt != "WEBP" or frames < 2:
        return (f"{page}: animation {src} is a {fmt} of {frames} frame{'s' * (frames != 1)}; expected an "
                f"animated WebP of the test sequence (more than one frame)")
    return None


def kind_problems(page: Path, drv) -> list[str]:
    """What a reader cannot tell of a measured table's rows: a missing Kind column, a row without a
    kind, a row that its table's "What each row runs" list (`ul.runs`, same `data-key`) does not name,
    as the browser shows them (a cell's text, a list item's method)."""
    tables = drv.execute_script(
        "return Array.from(document.querySelectorAll('table.measured')).map(function (t, i) { "
        "var key = t.dataset.key || '#' + i, list = Array.from(document.querySelectorAll('ul.runs')).filter("
        "function (u) { return u.dataset.key === key; })[0]; "
        "return [key, Array.from(t.tHead.rows[0].cells).map(function (c) { return c.textContent.trim(); }), "
        "Array.from(t.tBodies[0].rows).map(function (r) { return Array.from(r.cells).map("
        "function (c, j) { return j === 0 && c.dataset.v !== undefined ? c.dataset.v : c.textContent.trim(); }); }), "
        "list ? Array.from(list.querySelectorAll('li b')).map(function (b) { return b.textContent.trim(); }) "
        ": null]; })")
    problems = []
    for key, heads, rows, listed in tables:
        if "Kind" not in heads:
            problems.append(f"{page}: measured table {key} has no Kind column")
        else:
            col = heads.index("Kind")
            problems += [f"{page}: measured table {key}: row {row[0] if row else i} has no kind" for i, row in
                         enumerate(rows) if len(row) <= col or not row[col]]
        if listed is None:
            problems.append(f"{page}: measured table {key} has no \"What each row runs\" list (ul.runs)")
            continue
        methods = [row[0] for row in rows if row]
        if sorted(listed) != sorted(methods):
            problems.append(f"{page}: measured table {key}: its \"What each row runs\" list names "
                            f"{', '.join(listed) or 'no row'}; expected one line per row ({', '.join(methods)})")
    return problems


#: What the browser measures for `layout_problems`, as the page is first shown: the tables in
#: document order, and per shown measured table its fit, sticky column, legend and switch.
_LAYOUT_JS = """
// in a closed <details> an element still has boxes (content-visibility), so that is asked as well
function shown(el) { return el.getClientRects().length > 0 && !el.closest('details:not([open])'); }
var tables = Array.from(document.querySelectorAll('table'));
var out = {width: window.innerWidth, tables: tables.map(function (t) {
  return {measured: t.classList.contains('measured'), key: t.dataset.key || '', protocol: t.dataset.protocol || '',
          shown: shown(t)}; }), boards: []};
tables.filter(function (t) { return t.classList.contains('measured') && shown(t); }).forEach(function (t) {
  var wrap = t.parentElement, box = t.closest('section') || document.body;
  var heads = function () { return Array.from(t.tHead.rows[0].cells).filter(shown); };
  var legend = Array.from(box.querySelectorAll('.legend')).filter(function (l) {
    return l.compareDocumentPosition(t) & Node.DOCUMENT_POSITION_FOLLOWING; })[0];
  var link = legend && Array.from(legend.querySelectorAll('a')).some(function (a) {
    return (a.getAttribute('href') || '').indexOf('docs/metrics.md') >= 0; });
  var cell = t.tBodies[0].rows[0] ? t.tBodies[0].rows[0].cells[0] : t.tHead.rows[0].cells[0];
  var style = getComputedStyle(cell), before = heads();
  var b = {key: t.dataset.key || '', scroll: wrap.scrollWidth, client: wrap.clientWidth,
           right: Math.max.apply(null, before.map(function (h) { return h.getBoundingClientRect().right; })),
           shownHeads: before.length, allHeads: t.tHead.rows[0].cells.length,
           position: style.position, left: style.left, background: style.backgroundColor,
           legend: legend ? legend.textContent.trim() : null, legendLink: !!link, switchShows: null, stuck: null};
  var sw = Array.from(box.querySelectorAll('input.allcols')).filter(function (i) {
    return i.compareDocumentPosition(t) & Node.DOCUMENT_POSITION_FOLLOWING; })[0];
  if (sw) {  // "all columns": every heading shown; scrolled to the far right, the method cell stays put
    sw.click();
    b.switchShows = heads().length;
    if (wrap.scrollWidth > wrap.clientWidth) {
      wrap.scrollLeft = wrap.scrollWidth;
      b.stuck = cell.getBoundingClientRect().left - wrap.getBoundingClientRect().left;
      wrap.scrollLeft = 0;
    }
    sw.click();
  }
  out.boards.push(b);
});
return out;
"""


def _version(ref: str) -> tuple[str, int] | None:
    pid, _, v = ref.rpartition("@")
    return (pid, int(v)) if pid and v.isdigit() else None


def layout_problems(page: Path, drv) -> list[str]:
    """What keeps the page from reading at a glance at the viewport's width (`_LAYOUT_JS`): the
    first table not the current protocol's, an older version's table shown, and per shown measured
    table: no legend line above it, a default view wider than the viewport, hidden columns with no
    switch to show them, a method column that is not sticky."""
    got = drv.execute_script(_LAYOUT_JS)
    problems, width = [], got["width"]
    measured = [t for t in got["tables"] if t["measured"]]
    if measured:
        refs = [_version(t["protocol"]) for t in measured]
        problems += [f"{page}: measured table {t['key']} has no protocol id@version (data-protocol)"
                     for t, ref in zip(measured, refs) if ref is None]
        newest: dict[str, int] = {}
        for pid, v in filter(None, refs):
            newest[pid] = max(v, newest.get(pid, v))
        first = got["tables"][0]
        ref = _version(first["protocol"])
        if not first["measured"] or not first["shown"]:
            problems.append(f"{page}: the first table on the page is not a shown measured table")
        elif ref and ref[1] != newest[ref[0]]:
            problems.append(f"{page}: the first table on the page is {first['protocol']}, not the current version "
                            f"{ref[0]}@{newest[ref[0]]}")
        problems += [f"{page}: measured table {t['key']} of an older protocol version ({t['protocol']}) is shown; "
                     f"expected it folded (<details>)" for t, r in zip(measured, refs)
                     if r and r[1] != newest[r[0]] and t["shown"]]
    for b in got["boards"]:
        where = f"{page}: measured table {b['key']}"
        if not b["legend"]:
            problems.append(f"{where} has no legend line above it (.legend) on one-sided intervals")
        elif "one-sided" not in b["legend"].lower() or not b["legendLink"]:
            problems.append(f"{where}: its legend does not say which intervals are one-sided with a link to "
                            f"docs/metrics.md: {b['legend']!r}")
        if b["scroll"] > b["client"] or b["right"] > width:
            problems.append(f"{where}: its default columns do not fit a {width} px viewport (table {b['scroll']} px "
                            f"in {b['client']} px, last heading ends at {b['right']:.0f} px)")
        if b["shownHeads"] < b["allHeads"] and b["switchShows"] is None:
            problems.append(f"{where}: {b['allHeads'] - b['shownHeads']} hidden columns and no \"all columns\" "
                            f"switch (input.allcols)")
        elif b["switchShows"] is not None and b["switchShows"] < b["allHeads"]:
            problems.append(f"{where}: its \"all columns\" switch shows {b['switchShows']} of {b['allHeads']} "
                            f"columns")
        if b["position"] != "sticky" or b["left"] != "0px" or b["background"] in ("transparent", "rgba(0, 0, 0, 0)"):
            problems.append(f"{where}: the method column is not sticky at left 0 with a background (position "
                            f"{b['position']}, left {b['left']}, background {b['background']})")
        elif b["stuck"] is not None and abs(b["stuck"]) > 2:
            problems.append(f"{where}: scrolled sideways, the method column moved {b['stuck']:.0f} px out of view")
    return problems


def check_page(page: Path, screenshot: Path, *, expect_measured: bool = False, expect_animation: bool = False,
               timeout: float = 30.0) -> list[str]:
    """Problems found on `page` (empty: it passed); writes `screenshot`."""
    from selenium.webdriver.common.by import By

    problems: list[str] = []
    drv = _driver(WIDTH, HEIGHT)
    try:
        drv.get(page.resolve().as_uri())
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:  # images load asynchronously
            if drv.execute_script("return document.readyState === 'complete' && "
                                  "Array.from(document.images).every(function (i) { return i.complete; })"):
                break
            time.sleep(0.2)
        else:
            problems.append(f"{page}: not loaded after {timeout:.0f} s")
        images = drv.execute_script("return Array.from(document.images).map(function (i) { "
                                    "return [i.getAttribute('src'), i.naturalWidth]; })")
        problems += [f"{page}: image {src} did not load (naturalWidth 0)" for src, w in images if not w]
        animations = drv.execute_script("return Array.from(document.querySelectorAll('img.sequence')).map("
                                        "function (i) { return [i.getAttribute('src'), i.naturalWidth]; })")
        for src, w in animations:
            if not w:
                problems.append(f"{page}: animation {src} was not decoded by the browser (naturalWidth 0)")
            problems += [p for p in [animation_problem(page, src)] if p]
        if expect_animation and not animations:
            problems.append(f"{page}: no sequence animation (expected an <img class=\"sequence\">: run "
                            f"`skyeyes-bench leaderboard` after `leaderboard add` saved a test sequence)")
        tables = drv.find_elements(By.CSS_SELECTOR, "table")
        if not tables:
            problems.append(f"{page}: no table")
        for i, t in enumerate(tables):
            if not t.find_elements(By.CSS_SELECTOR, "tbody tr"):
                problems.append(f"{page}: table {i} has no rows")
        if expect_measured and not drv.find_elements(By.CSS_SELECTOR, "table.measured tbody tr"):
            problems.append(f"{page}: no measured table (expected one)")
        problems += kind_problems(page, drv)
        problems += layout_problems(page, drv)
        heads = [h for h in drv.find_elements(By.CSS_SELECTOR, "table.sortable th") if h.is_displayed()]
        if heads:
            heads[min(3, len(heads) - 1)].click()  # sort by a metric column: the page's own script runs
        for entry in drv.get_log("browser"):
            if entry.get("level") == "SEVERE":
                problems.append(f"{page}: console error: {entry.get('message')}")
        height = int(drv.execute_script("return document.documentElement.scrollHeight"))
        drv.set_window_size(WIDTH, min(max(height, 600), 12000))
        screenshot.parent.mkdir(parents=True, exist_ok=True)
        if not drv.save_screenshot(str(screenshot)):
            problems.append(f"{screenshot}: screenshot not written")
        print(f"{page}: {len(tables)} tables, {len(images)} images ({len(animations)} animations); "
              f"screenshot {screenshot}")
    finally:
        drv.quit()
    return problems


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("page", nargs="?", default=str(ROOT / "leaderboard" / "index.html"), help="the HTML page")
    ap.add_argument("--screenshot", help="where to write the full-page PNG (default: a temporary file)")
    ap.add_argument("--expect-measured", action="store_true", help="fail unless a measured table is shown")
    ap.add_argument("--expect-animation", action="store_true", help="fail unless a sequence animation is shown")
    args = ap.parse_args(argv)
    page = Path(args.page)
    if not page.is_file():
        print(f"{page}: page not found", file=sys.stderr)
        return 1
    missing = _missing()
    if missing:
        if os.environ.get("CI") == "true":
            print(f"leaderboard page check FAILED: {missing} (CI=true: the check must run)", file=sys.stderr)
            return 1
        print(f"leaderboard page check skipped: {missing}", file=sys.stderr)
        return 0
    shot = Path(args.screenshot) if args.screenshot else Path(tempfile.mkdtemp(prefix="leaderboard-page-")) / "page.png"
    problems = check_page(page, shot, expect_measured=args.expect_measured, expect_animation=args.expect_animation)
    for p in problems:
        print(p, file=sys.stderr)
    print("leaderboard page check " + ("FAILED" if problems else "passed"), file=sys.stderr if problems else sys.stdout)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
