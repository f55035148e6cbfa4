"""Leaderboard: reported tables equal the paper's; `leaderboard add` files checked results with
strip frames; measured tables rank with marks (paired replicates, else the fallback); plots
carry the Pareto front; strips have one tile per frame; the output is deterministic and
`--check` catches stale files."""

import json
import re
import shutil

import numpy as np
from pathlib import Path

import pytest
from conftest import ROOT, run_cli
from builders.evaluation import blurred_submission, make_dataset, protocol_env

from skyeyes_bench import leaderboard
from skyeyes_bench.leaderboard import marks, plots

#: The paper's two results tables, copied verbatim from its LaTeX source (the file says which lines).
PAPER = Path(__file__).parent / "paper" / "skyeyes-wacv2025-tables.tex"


def _paper_table(label):
    tex = PAPER.read_text()
    end = tex.index(f"\\label{{{label}}}")
    body = tex[tex.rindex("\\begin{tabular}", 0, end):end]
    rows = {}
    for m in re.finditer(r"\n\s*([A-Za-z0-9-]+)[^&\n]*(?:\n\s*)?((?:&\s*[\\\w{}.]+\s*){6})\\\\", body):
        vals = [float(re.sub(r"\\textbf\{([\d.]+)\}", r"\1", v).strip()) for v in m.group(2).split("&")[1:]]
        rows[m.group(1)] = vals
    return rows


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
    """Results of three methods (two identical) on a 3-scene, 6-sequence dataset (at least 5
    clusters: intervals exist), filed with `leaderboard add` into a leaderboard folder that also
    holds the reported tables."""
    tmp = tmp_path_factory.mktemp("lb")
    with protocol_env(tmp) as mp:
        from skyeyes_bench.data.layout import open_dataset
        from skyeyes_bench.evaluate import evaluate

        ds = open_dataset(make_dataset(tmp / "ds", scenes=3, seqs=2))
        root = tmp / "leaderboard"
        shutil.copytree(ROOT / "leaderboard" / "reported", root / "reported")
        for name, sigma in (("sharp", 0.6), ("blurry", 1.5), ("blurry-twin", 1.5)):
            sub = blurred_submission(ds, tmp / name, sigma=sigma, method=name)
            evaluate(sub, data=ds.root, out=tmp / f"{name}.results.json", progress=False)
            run_cli("leaderboard", "add", str(tmp / f"{name}.results.json"), "--root", str(root))
        yield root, mp


def _fresh(board, tmp_path, names=("blurry", "blurry-twin")) -> Path:
    """A leaderboard folder with the reported tables and copies of some filed results, without
    replicates (the fallback rules decide unless a test writes replicates itself)."""
    root, _ = board
    lb = tmp_path / "lb"
    shutil.copytree(root / "reported", lb / "reported")
    (lb / "results").mkdir()
    for n in names:
        d = json.loads((root / "results" / f"{n}.json").read_text())
        for m in d["metrics"].values():
            m.pop("replicates", None)
        (lb / "results" / f"{n}.json").write_text(json.dumps(d))
    return lb


def test_generate_mark_and_check(board):
    root, mp = board
    run_cli("leaderboard", "--root", str(root))
    md = (root / "README.md").read_text()
    sharp = next(ln for ln in md.splitlines() if ln.startswith("| sharp |"))
    # sharp is best on PSNR and SSIM, credibly (4 sequences, all better): bold, no dagger
    cells = sharp.split(" | ")
    assert cells[1] == "beyond the paper"  # Kind: a method id the paper does not have
    assert cells[3].startswith("**") and cells[4].startswith("**") and "†" not in cells[3]
    assert "3.00 (1.00 + 2.00)" in sharp  # run time: fit 1 + render 2 as the submission reports
    assert "evaltest@1 — measured" in md and "Marks decided by: PSNR, SSIM" in md
    # reported rows live in their own section, never in the measured table
    measured, reported = md.split("## Reported in papers")
    assert "Skyeyes" not in measured and "| Skyeyes | 54.73 | **32.22** |" in reported
    assert "No measured rows yet for protocol: `carla-town04`, `citysample-region5`, `synthtown`" in measured
    # the papers' tables open with the one line on why their PSNR does not read against ours
    assert "(13-17 dB on the measured rows)" in reported.split("### ")[0]
    assert "](../docs/metrics.md#what-the-paper-leaves-open)" in reported.split("### ")[0]
    html = (root / "index.html").read_text()
    reported_html = html.split("Reported in papers")[1].split("<h3")[0]
    assert "(13-17 dB on the measured rows)" in reported_html
    assert 'href="../docs/metrics.md#what-the-paper-leaves-open"' in reported_html
    assert "<script>" in html and 'class="sortable measured"' in html and "http" not in html.replace("http-equiv", "")
    for m in ("psnr", "ssim", "fid", "kid", "fvd", "kvd"):  # lpips: unavailable without weights
        assert (root / "plots" / f"evaltest@1-{m}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert f'src="plots/evaltest@1-{m}.png"' in html and f"(plots/evaltest@1-{m}.png)" in md
    assert 'src="strips/evaltest@1.png"' in html and "(strips/evaltest@1.png)" in md
    # deterministic: regenerating gives identical bytes; --check passes
    before = {p: p.read_bytes() for p in root.rglob("*") if p.is_file() and "results" not in p.parts}
    run_cli("leaderboard", "--root", str(root))
    assert before == {p: p.read_bytes() for p in before}
    run_cli("leaderboard", "--root", str(root), "--check")
    # a stale file, plot or strip makes --check exit 1
    (root / "README.md").write_text(md + "edited\n")
    (root / "plots" / "old.png").write_bytes(b"x")
    (root / "strips" / "old.png").write_bytes(b"x")
    rc, out, err = run_cli("leaderboard", "--root", str(root), "--check", check=1)
    assert "README.md (differs)" in err and "plots/old.png (no longer generated)" in err
    assert "strips/old.png (no longer generated)" in err
    (root / "README.md").write_text(md)
    (root / "plots" / "old.png").unlink()
    (root / "strips" / "old.png").unlink()


def test_add_files_a_result_with_its_frames_and_refuses_overwrite(board, tmp_path):
    root, _ = board
    src = root.parent / "sharp.results.json"
    filed = json.loads((root / "results" / "sharp.json").read_text())
    original = json.loads(src.read_text())
    assert filed.pop("leaderboard")["added_from"] == str(src.resolve())
    assert filed == original  # filed unchanged apart from what `add` says it added
    # frames: fewer scenes (3) than frames (4), so 4 evenly spaced of the 6 sequences (numbers 0, 1,
    # 3, 4), each its middle frame (index 8 of 16)
    (key,) = [p.name for p in (root / "frames").iterdir()]
    assert key.startswith("evaltest@1_")
    chosen = json.loads((root / "frames" / key / "frames.json").read_text())["frames"]
    seqs = original["dataset"]["sequences"]
    assert [(f["sequence"], f["index"]) for f in chosen] == [(seqs[q], 8) for q in (0, 1, 3, 4)]
    for who in ("ground-truth", "sharp", "blurry", "blurry-twin"):
        assert sorted(p.name for p in (root / "frames" / key / who).iterdir()) == [f"{j}.png" for j in range(4)] + [
            "sequence.webp"]  # the test sequence's animation: test_leaderboard_sequence.py
    gt = np.asarray(__import__("PIL.Image").Image.open(root / "frames" / key / "ground-truth" / "0.png"))
    from skyeyes_bench import imagefiles

    truth = imagefiles.read_image_uint8(Path(original["dataset"]["root"]) / chosen[0]["scene"] / chosen[0]["file"])
    assert np.array_equal(gt, truth[..., :3])  # 32 px frames are small already: copied as they are
    # a second add under the same name is refused in one line; --force replaces it
    rc, out, err = run_cli("leaderboard", "add", str(src), "--root", str(root), check=2)
    assert err.count("\n") == 1 and "already filed as 'sharp'" in err and "--force" in err
    run_cli("leaderboard", "add", str(src), "--root", str(root), "--force")
    # --name files it under another name; without the submission on the machine there are no frames
    doc = dict(original, submission=dict(original["submission"], path=str(tmp_path / "gone")))
    (tmp_path / "r.json").write_text(json.dumps(doc))
    lb = _fresh(board, tmp_path, names=())
    shutil.copytree(root / "frames", lb / "frames")
    rc, out, err = run_cli("leaderboard", "add", str(tmp_path / "r.json"), "--root", str(lb), "--name", "elsewhere")
    assert "no frames for elsewhere" in out and (lb / "results" / "elsewhere.json").is_file()
    run_cli("leaderboard", "--root", str(lb))
    assert "The strip has no frames for: sharp" in (lb / "README.md").read_text()  # the method name


def _corrupt(doc, how):
    if how == "not results":
        return {"hello": 1}
    if how == "partial":
        doc["format"] = "skyeyes-bench/partial@1"
    elif how == "sharded":
        doc["shard"] = {"index": 0, "count": 2}
    elif how == "unknown protocol":
        doc["protocol"]["ref"] = "nosuch@1"
    elif how == "no fit time":
        del doc["submission"]["timings"]["fit_s"]
    elif how == "no timings":
        doc["submission"]["timings"] = None
    elif how == "negative render time":
        doc["submission"]["timings"]["render_s"] = -1
    elif how == "bad replicates":
        doc["metrics"]["psnr"]["replicates"] = "many"
    elif how == "changed protocol":
        doc["protocol"]["sha256"] = "0" * 64
    elif how == "bad kind":
        doc["submission"]["config"] = {"kind": "sota"}
    elif how == "bad components":
        doc["submission"]["config"] = {"components": "ACM, VCM"}
    return doc


@pytest.mark.parametrize("how, field", [
    ("not results", "'format'"), ("partial", "'format'"), ("sharded", "'shard'"),
    ("unknown protocol", "'protocol.ref'"), ("no fit time", "'submission.timings.fit_s'"),
    ("no timings", "'submission.timings.fit_s'"), ("negative render time", "'submission.timings.render_s'"),
    ("bad replicates", "'metrics.psnr.replicates'"), ("changed protocol", "'protocol.sha256'"),
    ("bad kind", "'submission.config.kind'"), ("bad components", "'submission.config.components'"),
    ("not json", None)])
def test_add_refuses_a_bad_results_file_in_one_line(board, tmp_path, how, field):
    root, _ = board
    bad = tmp_path / "bad.json"
    doc = json.loads((root.parent / "blurry.results.json").read_text())
    bad.write_text("{ not json" if how == "not json" else json.dumps(_corrupt(doc, how)))
    lb = _fresh(board, tmp_path, names=())
    rc, out, err = run_cli("leaderboard", "add", str(bad), "--root", str(lb), check=2)
    assert err.count("\n") == 1 and str(bad) in err, err
    assert field is None or f"field {field}" in err, err
    assert "partial" in err if how in ("partial", "sharded") else True
    assert not list((lb / "results").iterdir()) and not (lb / "frames").exists()


@pytest.mark.parametrize("how, field", [
    ("unknown protocol", "'protocol.ref'"), ("no fit time", "'submission.timings.fit_s'"),
    ("changed protocol", "'protocol.sha256'"), ("partial", "'format'"), ("val split", "'dataset.split'")])
def test_check_holds_a_row_committed_by_hand_to_what_add_checks(board, tmp_path, how, field):
    """A row that arrives by a pull request (a results file put straight into results/, no `add`)
    is refused by `leaderboard --check`, CI's gate, as `add` would refuse it."""
    lb = _fresh(board, tmp_path)
    run_cli("leaderboard", "--root", str(lb))
    run_cli("leaderboard", "--root", str(lb), "--check")  # the honest rows pass
    doc = json.loads((lb / "results" / "blurry.json").read_text())
    if how == "val split":
        doc["dataset"]["split"] = "val"
    else:
        doc = _corrupt(doc, how)
    bad = lb / "results" / "blurry.json"
    bad.write_text(json.dumps(doc))
    rc, out, err = run_cli("leaderboard", "--root", str(lb), "--check", check=2)
    assert err.count("\n") == 1 and str(bad) in err and f"field {field}" in err, err


def test_a_row_of_several_seeds_shows_their_spread(board, tmp_path):
    """A results file of `reproduce --seeds N` keeps its first seed's value and interval in the
    cell and adds `N seeds: mean ± sd` (numpy's mean and sample sd of the seed values); the page
    puts the spread on a line of its own."""
    import numpy as np

    lb = _fresh(board, tmp_path)
    p = lb / "results" / "blurry.json"
    doc = json.loads(p.read_text())
    psnr = doc["metrics"]["psnr"]["value"]
    vals = [psnr, psnr + 0.31, psnr - 0.12]
    doc["seeds"] = {"seeds": [0, 1, 2], "results": ["seed-0/results.json", "seed-1/results.json",
                                                     "seed-2/results.json"],
                    "metrics": {"psnr": {"values": vals, "mean": float(np.mean(vals)),
                                         "sd": float(np.std(vals, ddof=1)), "min": min(vals), "max": max(vals)}}}
    p.write_text(json.dumps(doc))
    run_cli("leaderboard", "--root", str(lb))
    want = f"3 seeds: {np.mean(vals):.2f} ± {np.std(vals, ddof=1):.2f}"
    row = next(ln for ln in (lb / "README.md").read_text().splitlines() if ln.startswith("| blurry |"))
    assert f"{psnr:.2f} [" in row and want in row, row
    twin = next(ln for ln in (lb / "README.md").read_text().splitlines() if ln.startswith("| blurry-twin |"))
    assert "seeds:" not in twin
    # the page: the spread on a line of its own under the interval, the seeds' count under the
    # method's name, and a line above the table saying what the spread is
    page = (lb / "index.html").read_text()
    spread = f"{np.mean(vals):.2f} ± {np.std(vals, ddof=1):.2f}"
    assert f"</small><small>{spread}</small></td>" in page and want not in page
    assert '<td data-v="blurry">blurry<small>3 seeds</small></td>' in page
    assert '<td data-v="blurry-twin">blurry-twin</td>' in page
    assert page.count("mean ± sd over its seeds") == 1
    run_cli("leaderboard", "--root", str(lb), "--check")


def test_choose_frames_is_evenly_spaced_and_from_the_dataset_only():
    # 8 scenes x 2 sequences of 5 frames (listed shuffled): the first sequence of scenes 0, 2, 4, 6, frame 2
    seqs = [f"s{i}/y{q}" for i in range(8) for q in range(2)]
    recs = [{"scene": f"s{k // 2}", "file": f"g/{k}-{i}.png", "sequence": k, "index": i}
            for k in range(16) for i in range(5)]
    doc = {"dataset": {"sequences": seqs}, "frames": recs[::-1]}
    got = leaderboard.choose_frames(doc)
    assert [(f["sequence"], f["index"]) for f in got] == [("s0/y0", 2), ("s2/y0", 2), ("s4/y0", 2), ("s6/y0", 2)]
    assert [f["tile"] for f in got] == ["0.png", "1.png", "2.png", "3.png"]


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("hib", [True, False])
def test_pareto_front_equals_brute_force(seed, hib):
    rng = np.random.default_rng(seed)
    n = 12
    xs = [float(v) for v in rng.integers(1, 6, n)]  # few distinct values: ties on both axes
    ys = [float(v) for v in rng.integers(0, 5, n)]
    better = (lambda a, b: a > b) if hib else (lambda a, b: a < b)
    want = set()
    for i in range(n):
        beaten = False
        for j in range(n):
            no_worse = xs[j] <= xs[i] and (ys[j] == ys[i] or better(ys[j], ys[i]))
            if no_worse and (xs[j], ys[j]) != (xs[i], ys[i]):
                beaten = True
        if not beaten:
            want.add(i)
    got = plots.pareto_front(xs, ys, hib)
    assert set(got) == want and len(got) == len(want)
    assert [xs[i] for i in got] == sorted(xs[i] for i in got)  # in run-time order, to connect


def _with_replicates(lb, advantage, twin):
    """Hand-made replicates (as `evaluate` writes them once the statistics change lands): blurry
    better than its twin by `advantage` on PSNR (higher is better) and FID (lower is better);
    blurry's replicates noisy around its value, the twin's made from them by `twin`."""
    rng = np.random.default_rng(0)
    docs = {n: json.loads((lb / "results" / f"{n}.json").read_text()) for n in ("blurry", "blurry-twin")}
    for m, sign in (("psnr", 1.0), ("fid", -1.0)):
        docs["blurry"]["metrics"][m]["value"] = docs["blurry-twin"]["metrics"][m]["value"] + sign * advantage
        base = docs["blurry"]["metrics"][m]["value"] + rng.normal(0, 0.3, 200)
        docs["blurry"]["metrics"][m]["replicates"] = [*base[:-1].tolist(), None]  # one undefined replicate
        docs["blurry-twin"]["metrics"][m]["replicates"] = twin(base, sign).tolist()
    for n, d in docs.items():
        (lb / "results" / f"{n}.json").write_text(json.dumps(d))


@pytest.mark.parametrize("interval", ["as evaluated", "percentile"])
def test_paired_replicates_mark_a_constant_shift_credible(board, tmp_path, interval):
    lb = _fresh(board, tmp_path)
    # twin worse by a constant on every replicate: PSNR lower by 0.05, FID higher by 0.05 -> credible,
    # although the replicates' spread (0.3) is far wider than the shift (an unpaired rule would dagger)
    _with_replicates(lb, 0.05, lambda r, sign: r - sign * 0.05)
    if interval == "percentile":  # bootstrap replicates (not half-sampling): their percentile interval
        for n in ("blurry", "blurry-twin"):
            d = json.loads((lb / "results" / f"{n}.json").read_text())
            d["statistics"]["interval"] = "percentile"
            (lb / "results" / f"{n}.json").write_text(json.dumps(d))
    (t,) = leaderboard.load_tables(lb)[0]
    assert t.rules["psnr"] == t.rules["fid"] == marks.RULE_REPLICATES
    assert t.rules["ssim"] == marks.RULE_SEQUENCES and t.rules["kid"] == marks.RULE_OVERLAP  # no replicates
    for m in ("psnr", "fid"):
        assert [t.rows[i].method for i in t.best[m]] == ["blurry"] and m not in t.not_credible
    run_cli("leaderboard", "--root", str(lb))
    md = (lb / "README.md").read_text()
    assert "PSNR, FID: paired bootstrap replicates" in md


def test_paired_replicates_dagger_when_they_overlap(board, tmp_path):
    lb = _fresh(board, tmp_path)
    # the twin's replicates are blurry's in reverse order: differences symmetric about 0 -> dagger
    _with_replicates(lb, 1e-6, lambda r, sign: r[::-1])
    (t,) = leaderboard.load_tables(lb)[0]
    assert t.rules["psnr"] == marks.RULE_REPLICATES
    assert "psnr" in t.not_credible and "fid" in t.not_credible
    # replicates made with other statistics cannot be paired: the fallback rule decides
    d = json.loads((lb / "results" / "blurry-twin.json").read_text())
    d["statistics"]["seed"] += 1
    (lb / "results" / "blurry-twin.json").write_text(json.dumps(d))
    (t,) = leaderboard.load_tables(lb)[0]
    assert t.rules["psnr"] == marks.RULE_SEQUENCES and t.rules["fid"] == marks.RULE_OVERLAP


def test_null_intervals_render_as_too_few_scenes(board, tmp_path):
    lb = _fresh(board, tmp_path)
    for n in ("blurry", "blurry-twin"):
        d = json.loads((lb / "results" / f"{n}.json").read_text())
        d["metrics"]["fid"]["interval"] = None  # no reason given: the default words
        d["metrics"]["psnr"].update(interval=None, interval_note="too few scenes (K=2)")
        (lb / "results" / f"{n}.json").write_text(json.dumps(d))
    run_cli("leaderboard", "--root", str(lb))
    md = (lb / "README.md").read_text()
    row = next(ln for ln in md.splitlines() if ln.startswith("| blurry |")).split(" | ")
    assert row[3].strip("*").endswith("(too few scenes (K=2))") and "[" not in row[3]
    assert row[6].strip("*").endswith("(too few scenes)") and "[" not in row[6]
    assert "no interval (too few scenes)" in md
    assert (lb / "plots" / "evaltest@1-fid.png").is_file()


def test_strip_has_one_tile_per_frame_and_row(board):
    root, _ = board
    run_cli("leaderboard", "--root", str(root))
    from PIL import Image

    img = np.asarray(Image.open(root / "strips" / "evaltest@1.png").convert("RGB"))
    rows, cols = 1 + 3, 4  # ground truth + sharp, blurry, blurry-twin; 4 frames
    assert img.shape == (plots.HEAD_H + rows * plots.TILE, plots.LABEL_W + cols * plots.TILE, 3)
    # the ground-truth row's first tile holds the frame (scaled 32 -> 126 px, nearest): not blank
    y0, x0 = plots.HEAD_H, plots.LABEL_W
    tile = img[y0 + 1:y0 + plots.TILE - 1, x0 + 1:x0 + plots.TILE - 1]
    assert tile.std() > 10


def test_identical_methods_get_the_not_credible_mark(board, tmp_path):
    lb = _fresh(board, tmp_path)
    # the two blurry twins tie exactly -> both bold, no dagger; perturb one PSNR a hair so the
    # best is unique but not credibly better than its twin -> dagger
    d = json.loads((lb / "results" / "blurry.json").read_text())
    d["metrics"]["psnr"]["value"] += 1e-6
    first = next(iter(d["sequences"]))
    d["sequences"][first]["psnr"] += 1e-6
    (lb / "results" / "blurry.json").write_text(json.dumps(d))
    measured, _ = leaderboard.load_tables(lb)
    t = measured[0]
    assert "psnr" in t.not_credible and len(t.best["psnr"]) == 1
    assert len(t.best["ssim"]) == 2 and "ssim" not in t.not_credible


def test_a_lone_row_is_not_bold(board, tmp_path):
    """One measured row: nothing to compare, so no cell is marked best (the page said "one row:
    nothing to compare" and still bolded every cell)."""
    lb = _fresh(board, tmp_path, names=("blurry",))
    measured, _ = leaderboard.load_tables(lb)
    t = measured[0]
    assert len(t.rows) == 1 and t.metrics
    assert t.best == {} and not t.not_credible
    assert all(t.rules[m] == marks.RULE_ONE_ROW for m in t.metrics if t.rows[0].values.get(m) is not None)


def test_differing_sample_counts_are_said_in_one_line(board, tmp_path):
    """Issue 39: a set metric scored on different sample counts gets one warning line, in the
    table whose rows differ and across tables; equal counts get none."""
    lb = _fresh(board, tmp_path)
    run_cli("leaderboard", "--root", str(lb))
    assert "different sample counts" not in (lb / "README.md").read_text()
    d = json.loads((lb / "results" / "blurry-twin.json").read_text())
    n = d["metrics"]["fvd"]["n"]
    d["metrics"]["fvd"]["n"] = 2 * n  # as if scored on twice the clips
    (lb / "results" / "blurry-twin.json").write_text(json.dumps(d))
    (t,) = leaderboard.load_tables(lb)[0]
    assert f"FVD {2 * n} clips (blurry-twin), {n} clips (blurry)" in t.note  # file order and "1/N" in t.note
    # ... and across tables: the twin under another protocol version is a table of its own
    d["protocol"]["ref"] = "evaltest@2"
    (lb / "results" / "blurry-twin.json").write_text(json.dumps(d))
    tables = leaderboard.load_tables(lb)[0]
    assert [t.key for t in tables] == ["evaltest@1", "evaltest@2"]
    assert all("different sample counts" not in t.note for t in tables)  # one row each
    run_cli("leaderboard", "--root", str(lb))
    md, html = (lb / "README.md").read_text(), (lb / "index.html").read_text()
    line = f"FVD {n} clips (evaltest@1), {2 * n} clips (evaltest@2)"
    assert sum(line in ln for ln in md.splitlines()) == 1 and line in html


def test_each_row_says_its_kind_what_it_runs_and_its_budget(board, tmp_path):
    """Issue 36 and after: the board says what each row is (a Kind column: the results' config
    "kind", else the paper's kind of its method id) and, one line per row under its table, what
    its method runs (config "components", else derived from a legacy config) and, for a
    diffusion row, its training budget; rows without ACM steps get no budget."""
    from skyeyes_bench.leaderboard.tables import training_budget

    lb = _fresh(board, tmp_path, names=("sharp", "blurry", "blurry-twin"))
    cfgs = {"blurry": dict(acm_steps=12000, acm_anneal=3000, acm_batch=16, train_crop=32, mixed_precision="bf16",
                           vcm=True, vcm_steps=3000, vcm_batch=1),
            "blurry-twin": dict(acm_steps=3000, acm_anneal=0, acm_batch=16, train_crop=32, mixed_precision="no",
                                vcm=False, vcm_steps=300, vcm_batch=1)}
    assert training_budget(cfgs["blurry"]) == ("ACM 12000 steps (rate decaying over the last 3000) at batch 16 on "
                                               "32-px crops, bf16, VCM 3000 steps at batch 1")
    assert training_budget(cfgs["blurry-twin"]) == "ACM 3000 steps at batch 16 on 32-px crops, fp32, no VCM"
    assert training_budget({**cfgs["blurry"], "vcm_snr_gamma": 0.0}).endswith("VCM 3000 steps at batch 1, uniform "
                                                                              "loss weights")
    assert training_budget({**cfgs["blurry"], "vcm_snr_gamma": -1.0}) == training_budget(cfgs["blurry"])
    assert training_budget({"iterations": 500}) == training_budget(None) == ""
    # blurry: the paper's method id, but its config says it is beyond the paper and what it runs;
    # blurry-twin: the ablation's id with a legacy config; sharp: the floor's id, no config at all
    edits = {"blurry": ("skyeyes", {**cfgs["blurry"], "kind": "beyond", "components": ["condition: a|b", "ACM"]}),
             "blurry-twin": ("skyeyes-no-vcm", {**cfgs["blurry-twin"], "condition": "prior", "prior_method": "sugar"}),
             "sharp": ("mean-frame", None)}
    for name, (method, cfg) in edits.items():
        d = json.loads((lb / "results" / f"{name}.json").read_text())
        d["submission"].update(method=method, config=cfg)
        (lb / "results" / f"{name}.json").write_text(json.dumps(d))
    run_cli("leaderboard", "--root", str(lb))
    md, page = (lb / "README.md").read_text(), (lb / "index.html").read_text()
    assert "Training budget of the diffusion rows" not in md
    lines = md.splitlines()
    (head,) = [i for i, ln in enumerate(lines) if ln.startswith("| Method | Kind | Version | PSNR ↑ |")]
    rows = [ln.split(" | ")[:2] for ln in lines[head + 2:head + 5]]
    assert rows == [["| mean-frame", "floor"], ["| skyeyes", "beyond the paper"],
                    ["| skyeyes-no-vcm", "paper's ablation"]]
    assert lines[head + 5] == ""
    runs = lines[lines.index("What each row runs:") + 2:][:4]
    assert runs == [  # the table's order (by method), Markdown in inputs escaped
        "- **mean-frame** (floor): every frame the per-pixel mean of the train split's ground frames",
        "- **skyeyes** (beyond the paper): condition: a\\|b; ACM — ACM 12000 steps (rate decaying over the last "
        "3000) at batch 16 on 32-px crops, bf16, VCM 3000 steps at batch 1",
        "- **skyeyes-no-vcm** (paper's ablation): condition: the sugar prior's renders; ACM frame by frame; pure "
        "Gaussian noise — ACM 3000 steps at batch 16 on 32-px crops, fp32, no VCM",
        ""]
    assert '<td class="kind" data-v="paper&#x27;s ablation">paper&#x27;s ablation</td>' in page
    assert ('<li data-method="skyeyes"><b>skyeyes</b> (beyond the paper): condition: a|b; ACM — ACM 12000 steps '
            "(rate decaying over the last 3000) at batch 16 on 32-px crops, bf16, VCM 3000 steps at batch 1</li>"
            ) in page
    assert ('<li data-method="mean-frame"><b>mean-frame</b> (floor): every frame the per-pixel mean of the train '
            'split&#x27;s ground frames</li>') in page
    # a config kind the board does not know is refused in one line naming the field
    d = json.loads((lb / "results" / "sharp.json").read_text())
    d["submission"]["config"] = {"kind": "paper's"}
    (lb / "results" / "sharp.json").write_text(json.dumps(d))
    rc, out, err = run_cli("leaderboard", "--root", str(lb), check=2)
    assert err.count("\n") == 1 and "sharp.json: field 'submission.config.kind': expected the row's kind" in err, err


def test_board_marks_reflect_fd_inf_about_the_centres(tmp_path):
    """Issue 39: the board's paired interval for FD∞ is `compare`'s, about the advantage of the two
    rows' interval centres (read from the results files), not about the values."""
    from skyeyes_bench import stats
    from skyeyes_bench.leaderboard.tables import measured_row

    rng = np.random.default_rng(0)
    ra, rb = 100 + rng.normal(size=70), 104 + rng.normal(size=70)
    st = {"interval": "half-sampling", "clusters": 8}
    est, centre = 3.0, 5.0  # B - A: lower is better
    got = marks.replicate_interval(ra, rb, "fid_inf", 0.95, estimate=est, statistics=st, centre=centre)
    lo, hi, _ = stats.interval_from_replicates(est, rb - ra, 0.95, 8, centre)
    assert got == (lo, hi) and got != marks.replicate_interval(ra, rb, "fid_inf", 0.95, estimate=est, statistics=st)
    doc = {"submission": {"method": "m"}, "sequences": {}, "metrics": {
        "fid_inf": {"status": "ok", "value": 1.0, "interval": [0.5, 1.5], "interval_centre": 1.25,
                    "replicates": [1.0, 1.1]},
        "fid": {"status": "ok", "value": 2.0, "interval": [1.5, 2.5], "replicates": [2.0, 2.1]}}}
    row = measured_row(doc, "m.json", ["fid_inf", "fid"])
    assert row.centres == {"fid_inf": 1.25}
