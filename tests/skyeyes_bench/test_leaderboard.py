"""Leaderboard: reported tables equal the paper's, measured tables rank with marks, the output
is deterministic and `--check` catches stale files."""

import json
import re
import shutil
from pathlib import Path

import pytest
from conftest import ROOT, run_cli
from builders.evaluation import blurred_submission, install_test_protocol, make_dataset

from skyeyes_bench import leaderboard

PAPER = Path("/work/shared/paper/skyeyes-wacv2025.tex")


def _paper_table(label):
    tex = PAPER.read_text()
    end = tex.index(f"\\label{{{label}}}")
    body = tex[tex.rindex("\\begin{tabular}", 0, end):end]
    rows = {}
    for m in re.finditer(r"\n\s*([A-Za-z0-9-]+)[^&\n]*(?:\n\s*)?((?:&\s*[\\\w{}.]+\s*){6})\\\\", body):
        vals = [float(re.sub(r"\\textbf\{([\d.]+)\}", r"\1", v).strip()) for v in m.group(2).split("&")[1:]]
        rows[m.group(1)] = vals
    return rows


@pytest.mark.skipif(not PAPER.is_file(), reason="paper source not available")
@pytest.mark.parametrize("toml, label", [("skyeyes-wacv2025-table1-citysample.toml", "tab:quant-region5"),
                                         ("skyeyes-wacv2025-table2-carla.toml", "tab:quant-carla")])
def test_reported_tables_equal_the_paper(toml, label):
    import tomllib

    raw = tomllib.loads((ROOT / "leaderboard" / "reported" / toml).read_text())
    paper = _paper_table(label)
    assert len(paper) == 8
    assert raw["status"] == "reported" and "WACV 2025" in raw["citation"]
    names = {"Ours": "Skyeyes"}
    assert [names.get(k, k) for k in paper] == [r["method"] for r in raw["rows"]]
    for (k, vals), row in zip(paper.items(), raw["rows"]):
        assert [row[m] for m in raw["metrics"]] == vals, k  # column order FID PSNR SSIM LPIPS KVD FVD


def test_committed_leaderboard_is_up_to_date():
    rc, out, err = run_cli("leaderboard", "--check", check=None)
    assert rc == 0, err


@pytest.fixture(scope="module")
def board(tmp_path_factory):
    """A leaderboard folder with three measured results (two identical methods) + the reported tables."""
    mp = pytest.MonkeyPatch()
    tmp = tmp_path_factory.mktemp("lb")
    try:
        install_test_protocol(tmp, mp)
        mp.setenv("SKYEYES_CACHE", str(tmp / "cache"))  # module scope: the per-test cache is not set yet
        from skyeyes_bench.data.layout import open_dataset
        from skyeyes_bench.evaluate import evaluate

        ds = open_dataset(make_dataset(tmp / "ds"))
        root = tmp / "leaderboard"
        shutil.copytree(ROOT / "leaderboard" / "reported", root / "reported")
        for name, sigma in (("sharp", 0.6), ("blurry", 1.5), ("blurry-twin", 1.5)):
            sub = blurred_submission(ds, tmp / name, sigma=sigma, method=name)
            evaluate(sub, data=ds.root, out=root / "results" / f"{name}.json", progress=False)
        yield root, mp
    finally:
        mp.undo()


def test_generate_mark_and_check(board, monkeypatch):
    root, mp = board
    monkeypatch.setenv("SKYEYES_PROTOCOLS", str(root.parent / "protocols"))
    run_cli("leaderboard", "--root", str(root))
    md = (root / "README.md").read_text()
    sharp = next(ln for ln in md.splitlines() if ln.startswith("| sharp |"))
    # sharp is best on PSNR and SSIM, credibly (4 sequences, all better): bold, no dagger
    cells = sharp.split(" | ")
    assert cells[2].startswith("**") and cells[3].startswith("**") and "†" not in cells[2]
    assert "evaltest@1 — measured" in md
    # reported rows live in their own section, never in the measured table
    measured, reported = md.split("## Reported in papers")
    assert "Skyeyes" not in measured and "| Skyeyes | 54.73 | **32.22** |" in reported
    html = (root / "index.html").read_text()
    assert "<script>" in html and 'class="sortable"' in html and "http" not in html.replace("http-equiv", "")
    assert (root / "plots" / "evaltest@1.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # deterministic: regenerating gives identical bytes; --check passes
    before = {p: p.read_bytes() for p in root.rglob("*") if p.is_file() and "results" not in p.parts}
    run_cli("leaderboard", "--root", str(root))
    assert before == {p: p.read_bytes() for p in before}
    run_cli("leaderboard", "--root", str(root), "--check")
    # a stale file or a stale plot makes --check exit 1
    (root / "README.md").write_text(md + "edited\n")
    (root / "plots" / "old.png").write_bytes(b"x")
    rc, out, err = run_cli("leaderboard", "--root", str(root), "--check", check=1)
    assert "README.md (differs)" in err and "plots/old.png (no longer generated)" in err
    (root / "README.md").write_text(md)


def test_identical_methods_get_the_not_credible_mark(board, monkeypatch):
    root, mp = board
    monkeypatch.setenv("SKYEYES_PROTOCOLS", str(root.parent / "protocols"))
    # drop the sharp one: the two blurry twins tie exactly -> both bold, no dagger; perturb one
    # PSNR a hair so the best is unique but not credibly better than its twin -> dagger
    lb = root.parent / "lb2"
    shutil.copytree(root / "reported", lb / "reported")
    (lb / "results").mkdir()
    for n in ("blurry", "blurry-twin"):
        shutil.copy(root / "results" / f"{n}.json", lb / "results")
    d = json.loads((lb / "results" / "blurry.json").read_text())
    d["metrics"]["psnr"]["value"] += 1e-6
    first = next(iter(d["sequences"]))
    d["sequences"][first]["psnr"] += 1e-6
    (lb / "results" / "blurry.json").write_text(json.dumps(d))
    measured, _ = leaderboard.load_tables(lb)
    t = measured[0]
    assert "psnr" in t.not_credible and len(t.best["psnr"]) == 1
    assert len(t.best["ssim"]) == 2 and "ssim" not in t.not_credible
