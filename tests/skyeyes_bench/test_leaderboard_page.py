"""The leaderboard page in a real headless browser (scripts/check-leaderboard-page.py): a board
with measured rows, plots, a strip and the sequence animation loads without console errors, every
image decodes, the animation has several frames, and every measured row shows its kind and is named
in the "What each row runs" list under its table.
Slow tier: starts Chromium. Fails (never skips) when CI=true and Chromium is missing."""

import importlib.util
import os
import shutil

import pytest
from conftest import ROOT, run_cli
from builders.evaluation import blurred_submission, install_test_protocol, make_dataset

pytestmark = pytest.mark.slow


def _script():
    path = ROOT / "scripts" / "check-leaderboard-page.py"
    spec = importlib.util.spec_from_file_location("check_leaderboard_page", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _need_browser(mod):
    missing = mod._missing()
    if missing and os.environ.get("CI") == "true":
        pytest.fail(f"CI=true but the browser check cannot run: {missing}")
    if missing:
        pytest.skip(missing)


def test_page_with_measured_rows_loads_in_chromium(tmp_path, monkeypatch):
    mod = _script()
    _need_browser(mod)
    install_test_protocol(tmp_path, monkeypatch)
    from skyeyes_bench.data.layout import open_dataset
    from skyeyes_bench.evaluate import evaluate

    ds = open_dataset(make_dataset(tmp_path / "ds", scenes=3, seqs=2, frames=8))
    root = tmp_path / "leaderboard"
    shutil.copytree(ROOT / "leaderboard" / "reported", root / "reported")
    for name, sigma in (("sharp", 0.6), ("blurry", 1.5)):
        sub = blurred_submission(ds, tmp_path / name, sigma=sigma, method=name)
        evaluate(sub, data=ds.root, out=tmp_path / f"{name}.json", progress=False)
        run_cli("leaderboard", "add", str(tmp_path / f"{name}.json"), "--root", str(root))
    run_cli("leaderboard", "--root", str(root))
    shot = tmp_path / "page.png"
    problems = mod.check_page(root / "index.html", shot, expect_measured=True, expect_animation=True)
    assert problems == []
    assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the check can fail: an animation of one frame (a still WebP: every frame the same)
    animation = root / "strips" / "evaltest@1-sequence.webp"
    from PIL import Image

    moving = animation.read_bytes()
    with Image.open(animation) as im:
        im.seek(1)
        im.convert("RGB").save(animation, format="WEBP")
    problems = mod.check_page(root / "index.html", shot, expect_animation=True)
    assert problems == [f"{root / 'index.html'}: animation strips/evaltest@1-sequence.webp is a WEBP of 1 frame; "
                        f"expected an animated WebP of the test sequence (more than one frame)"]
    animation.write_bytes(moving)
    # the check can fail: a row without a kind, a row its "What each row runs" list does not name, a
    # table without a Kind column or without the list
    page = (root / "index.html").read_text()
    assert page.count("<th>Kind</th>") == 1 and page.count('<li data-method="sharp">') == 1
    (root / "index.html").write_text(page.replace('<td class="kind" data-v="beyond the paper">beyond the paper</td>', "<td></td>", 1)
                                     .replace('<li data-method="sharp"><b>sharp</b>', "<li><b>blunt</b>"))
    problems = mod.check_page(root / "index.html", shot)
    assert problems == [f"{root / 'index.html'}: measured table evaltest@1: row blurry has no kind",
                        f"{root / 'index.html'}: measured table evaltest@1: its \"What each row runs\" list names "
                        f"blurry, blunt; expected one line per row (blurry, sharp)"]
    (root / "index.html").write_text(page.replace("<th>Kind</th>", "<th>Sort</th>").replace('class="runs', 'class="'))
    problems = mod.check_page(root / "index.html", shot)
    where = f"{root / 'index.html'}: measured table evaltest@1"
    assert problems == [f"{where} has no Kind column", f"{where} has no \"What each row runs\" list (ul.runs)"]
    (root / "index.html").write_text(page)
    # the check can fail: a missing plot is a console error and an image of naturalWidth 0
    next((root / "plots").glob("*.png")).unlink()
    problems = mod.check_page(root / "index.html", shot, expect_measured=True)
    assert any("did not load" in p for p in problems) and any("console error" in p for p in problems)
    # ... and so is a missing animation: not decoded by the browser, not readable
    animation.unlink()
    problems = mod.check_page(root / "index.html", shot)
    assert any("animation strips/evaltest@1-sequence.webp was not decoded" in p for p in problems)
    assert any("animation strips/evaltest@1-sequence.webp cannot be read" in p for p in problems)
    # a page without an animation fails only when one is expected
    (root / "index.html").write_text((root / "index.html").read_text().replace('class="strip sequence"', 'hidden'))
    problems = mod.check_page(root / "index.html", shot, expect_animation=True)
    assert any("no sequence animation" in p for p in problems)


def test_committed_page_loads_in_chromium(tmp_path):
    mod = _script()
    _need_browser(mod)
    assert mod.check_page(ROOT / "leaderboard" / "index.html", tmp_path / "page.png") == []
