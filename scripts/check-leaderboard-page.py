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
names every row of its table, and a click on a column heading sorts without an error. Writes a
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
        "function (c) { return c.textContent.trim(); }); }), "
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


def check_page(page: Path, screenshot: Path, *, expect_measured: bool = False, expect_animation: bool = False,
               timeout: float = 30.0) -> list[str]:
    """Problems found on `page` (empty: it passed); writes `screenshot`."""
    from selenium.webdriver.common.by import By

    problems: list[str] = []
    drv = _driver(1400, 1000)
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
        heads = drv.find_elements(By.CSS_SELECTOR, "table.sortable th")
        if heads:
            heads[min(3, len(heads) - 1)].click()  # sort by a metric column: the page's own script runs
        for entry in drv.get_log("browser"):
            if entry.get("level") == "SEVERE":
                problems.append(f"{page}: console error: {entry.get('message')}")
        height = int(drv.execute_script("return document.documentElement.scrollHeight"))
        drv.set_window_size(1400, min(max(height, 600), 12000))
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
