"""evaluate / merge / compare on a tiny dataset with the test protocol (random-* extractors).

Expected values come from independent computations: scikit-image PSNR/SSIM, scipy sqrtm FID."""

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli
from skimage.metrics import peak_signal_noise_ratio, structural_similarity
from builders.evaluation import SCENE_PROTOCOL, blurred_submission, make_dataset, protocol_env, scipy_fid, scores

from skyeyes_bench import comparison, imagefiles
from skyeyes_bench.data.layout import open_dataset
from skyeyes_bench.errors import UserError
from skyeyes_bench.evaluate import evaluate, features_path, read_results
from skyeyes_bench.submission import expected_frames, write_template


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    # 3 scenes x 2 sequences: evaltest@1 resamples sequences (K = 6 >= 5: intervals are given)
    return make_dataset(tmp_path_factory.mktemp("ds") / "evaltiny", scenes=3)


@pytest.fixture(scope="module")
def scored(tmp_path_factory, tiny):
    """Results of the perfect submission and of blurs sigma 0.7 and 1.5, evaluated once."""
    tmp = tmp_path_factory.mktemp("scored")
    with protocol_env(tmp):
        ds = open_dataset(tiny)
        subs = {"gt": write_template(ds, tmp / "gt", from_ground_truth=True),
                "b1": blurred_submission(ds, tmp / "b1", sigma=0.7),
                "b2": blurred_submission(ds, tmp / "b2", sigma=1.5)}
        res = {k: evaluate(v, data=tiny, out=tmp / f"{k}.json", progress=False) for k, v in subs.items()}
        yield ds, subs, res, tmp


def test_perfect_and_blurred(scored):
    ds, subs, res, tmp_path = scored
    blur, rp, rb = subs["b2"], res["gt"], res["b2"]
    mp, mb = rp["metrics"], rb["metrics"]
    assert list(mp) == ["psnr", "ssim", "lpips", "fid", "kid", "fvd", "kvd"]
    # perfect: PSNR inf, SSIM 1, FID / FVD 0
    assert mp["psnr"]["value"] == math.inf and mp["psnr"]["infinite_frames"] == 96
    assert mp["ssim"]["value"] == pytest.approx(1.0, abs=1e-12)
    assert mp["fid"]["value"] == pytest.approx(0.0, abs=1e-6)
    assert mp["fvd"]["value"] == pytest.approx(0.0, abs=1e-6)
    # LPIPS weights are absent here: reported unavailable with the reason and the fix
    assert mp["lpips"]["status"] == "unavailable" and mp["lpips"]["reason"] and mp["lpips"]["fix"]
    # blurred: strictly worse on every metric
    assert mb["psnr"]["value"] < math.inf and mb["ssim"]["value"] < mp["ssim"]["value"]
    for m in ("fid", "kid", "fvd", "kvd"):
        assert mb[m]["value"] > mp[m]["value"] + 1e-9, m
    # the numbers, recomputed independently
    scene, f = expected_frames(ds)[9]
    pred = imagefiles.read_image(blur / scene / f.file).astype(np.float64)
    gt = f.image().astype(np.float64)
    rec = next(r for r in rb["frames"] if r["scene"] == scene and r["file"] == f.file)
    assert rec["psnr"] == pytest.approx(peak_signal_noise_ratio(gt, pred, data_range=1.0), rel=1e-6)
    want = structural_similarity(gt, pred, win_size=11, gaussian_weights=True, sigma=1.5, data_range=1.0,
                                 channel_axis=2, use_sample_covariance=False)
    assert rec["ssim"] == pytest.approx(want, abs=1e-5)
    assert mb["psnr"]["value"] == pytest.approx(np.mean([r["psnr"] for r in rb["frames"]]))
    _, feats = read_results(tmp_path / "b2.json", features=True)
    x = feats["random-image-64"]
    assert x["sub"].shape == (96, 64)
    assert mb["fid"]["value"] == pytest.approx(scipy_fid(x["sub"], x["gt"]), rel=1e-5)
    v = feats["random-video-64"]
    assert v["sub"].shape == (24, 64)  # 6 sequences x 16 frames / clips of 4 every 4
    assert mb["fvd"]["value"] == pytest.approx(scipy_fid(v["sub"], v["gt"]), rel=1e-5)
    # intervals contain their own value (set metrics too); replicates: R of them, rounded
    st = rb["statistics"]
    assert st["cluster"] == "sequence" and st["clusters"] == 6 and st["interval"] == "half-sampling"
    assert st["too_few"] is None
    for m in ("psnr", "ssim", "fid", "kid", "fvd", "kvd"):
        lo, hi = mb[m]["interval"]
        assert lo <= mb[m]["value"] <= hi, m
        assert len(mb[m]["replicates"]) == 200 and all(isinstance(r, float) for r in mb[m]["replicates"]), m
    # self-description
    assert rb["protocol"]["ref"] == "evaltest@1" and len(rb["protocol"]["sha256"]) == 64
    assert rb["extractors"]["random-image-64"]["status"] == "ok"
    assert rb["sha256"]["ground_truth"] == rp["sha256"]["ground_truth"]
    assert rb["sha256"]["submission_frames"] != rp["sha256"]["submission_frames"]
    assert rb["submission"]["timings"]["fit_s"] == 1.0
    assert set(rb["sequences"]) == {f"test-0-lane0{i}/yaw{q:03d}" for i in (0, 1, 2) for q in (0, 90)}
    assert {"validate_s", "frame_metrics_s", "features_s", "bootstrap_s", "total_s"} <= set(rb["timing_s"])
    on_disk = json.loads((tmp_path / "b2.json").read_text())
    assert on_disk["metrics"]["fid"]["value"] == mb["fid"]["value"]


def test_existing_results_need_force(tiny, scored, tmp_path):
    blur = scored[1]["b1"]
    out = tmp_path / "r.json"
    out.write_text("{}")
    rc, _, err = run_cli("evaluate", "--allow-missing", str(blur), "--data", str(tiny), "--out", str(out), "--quiet", check=2)
    assert "already exists; pass --force" in err and out.read_text() == "{}"
    run_cli("evaluate", "--allow-missing", str(blur), "--data", str(tiny), "--out", str(out), "--quiet", "--force")
    assert json.loads(out.read_text())["format"] == "skyeyes-bench/results@1"
    assert features_path(out).is_file()


def test_shards_merge_to_the_unsharded_numbers(tiny, scored, tmp_path):
    blur, full = scored[1]["b1"], scored[2]["b1"]
    parts = []
    for i in (1, 0, 2):  # order does not matter; 3 shards over 4 sequences
        p = tmp_path / f"part{i}.json"
        run_cli("evaluate", "--allow-missing", str(blur), "--data", str(tiny), "--out", str(p), "--shard", f"{i}/3", "--quiet")
        parts.append(str(p))
    rc, out, err = run_cli("merge", *parts[:2], "--out", str(tmp_path / "m.json"), "--quiet", check=2)
    assert "shards 2/3 missing" in err
    run_cli("merge", *parts, "--out", str(tmp_path / "merged.json"), "--quiet")
    merged, _ = read_results(tmp_path / "merged.json")
    # to the last digit: every value, interval and replicate, per-sequence and per-frame value
    # (features computed afresh: this test's own cache; a frame's do not depend on its batch)
    assert scores(merged) == scores(full)


def test_official_protocol_refuses_random_extractors():
    from skyeyes_bench.evaluate import check_extractors
    from skyeyes_bench.protocol import load_protocol

    p = load_protocol("synthtown@1")
    bad = p.__class__(**{**p.__dict__, "metrics": tuple(
        m.__class__(**{**m.__dict__, "extractor": "random-image-64"}) if m.name == "fid" else m
        for m in p.metrics)})
    with pytest.raises(UserError, match="test-only"):
        check_extractors(bad)


def test_compare_cli(scored, tmp_path):
    ds, subs, res, scored_dir = scored
    for k in ("gt", "b1", "b2"):
        shutil.copy(scored_dir / f"{k}.json", tmp_path)
        shutil.copy(scored_dir / f"{k}.features.npz", tmp_path)
    rc, out, err = run_cli("compare", str(tmp_path / "b1.json"), str(tmp_path / "b2.json"), "--json")
    res = json.loads(out)
    for m in ("psnr", "ssim"):
        assert res["metrics"][m]["bayes"]["p_a_better"] > 0.99, m  # less blur is better
        assert res["metrics"][m]["bootstrap_interval"][0] > 0
    for m in ("fid", "fvd"):
        assert res["metrics"][m]["advantage_mean"] > 0 and res["metrics"][m]["bootstrap_interval"][0] > 0
    assert res["metrics"]["lpips"]["status"] == "skipped"
    # identical: zero difference, P = 0.5, said so
    rc, out, err = run_cli("compare", str(tmp_path / "b1.json"), str(tmp_path / "b1.json"), "--json")
    res = json.loads(out)
    assert res["metrics"]["ssim"]["bayes"]["p_a_better"] == 0.5 and res["metrics"]["ssim"]["advantage_mean"] == 0
    assert res["metrics"]["fid"]["bootstrap_interval"] == [0.0, 0.0]
    assert res["metrics"]["fid"]["advantage"] == 0.0 and res["metrics"]["psnr"]["bootstrap_interval"] == [0.0, 0.0]
    # perfect vs blurred: PSNR differences are +inf on every sequence
    rc, out, err = run_cli("compare", str(tmp_path / "gt.json"), str(tmp_path / "b1.json"))
    assert "infinite difference" in out
    # different protocol version: refused, saying why
    doc = json.loads((tmp_path / "b2.json").read_text())
    doc["protocol"]["ref"] = "evaltest@2"
    (tmp_path / "b2v2.json").write_text(json.dumps(doc))
    rc, out, err = run_cli("compare", str(tmp_path / "b1.json"), str(tmp_path / "b2v2.json"), check=2)
    assert "different protocols or protocol versions" in err
    doc = json.loads((tmp_path / "b2.json").read_text())
    doc["extractors"]["random-image-64"]["weights_sha256"] = "f" * 64
    (tmp_path / "b2x.json").write_text(json.dumps(doc))
    rc, out, err = run_cli("compare", str(tmp_path / "b1.json"), str(tmp_path / "b2x.json"), check=2)
    assert "extractor random-image-64 used different weights" in err


def test_smoke_end_to_end(synthtown_smoke, tmp_path):
    """The real SynthTown smoke data under the official synthtown@1 protocol: the ground truth
    scores PSNR inf and SSIM 1; metrics without weights are reported unavailable."""
    sub = tmp_path / "gt"
    run_cli("submission", "template", "--data", str(synthtown_smoke), "--out", str(sub), "--from-ground-truth")
    out = tmp_path / "gt.json"
    rc, text, err = run_cli("evaluate", "--allow-missing", str(sub), "--data", str(synthtown_smoke), "--out", str(out), "--quiet")
    res, _ = read_results(out)
    assert res["protocol"]["ref"] == "synthtown@1"
    assert res["metrics"]["psnr"]["value"] == math.inf
    assert res["metrics"]["ssim"]["value"] == pytest.approx(1.0, abs=1e-12)
    for m, v in res["metrics"].items():
        if v["status"] == "unavailable":
            assert v["reason"] and v["fix"], m
            assert f"{m:<6} unavailable" in text


@pytest.mark.slow
@pytest.mark.weights
def test_done_when_real_extractors(synthtown_smoke, tmp_path):
    """Issue 5's 'done when' with the real Inception, I3D and LPIPS weights (linked in from where
    `skyeyes-bench weights fetch` put them): the ground truth scores PSNR inf, SSIM 1, LPIPS, FID
    and FVD 0; a blurred submission is strictly worse on every metric, and every metric is scored."""
    from builders.weights import require

    from skyeyes_bench.metrics.extractors import get_extractor

    require(*(f for ex in ("inception-tf-2015", "i3d-kinetics400", "lpips-alex-v0.1") for f in get_extractor(ex).files))
    ds = open_dataset(synthtown_smoke)
    rp = evaluate(write_template(ds, tmp_path / "gt", from_ground_truth=True), data=synthtown_smoke,
                  progress=False)["metrics"]
    rb = evaluate(blurred_submission(ds, tmp_path / "blur", sigma=1.5), data=synthtown_smoke,
                  progress=False)["metrics"]
    assert rp["psnr"]["value"] == math.inf and rp["ssim"]["value"] == pytest.approx(1.0)
    assert rp["fid"]["value"] == pytest.approx(0.0, abs=1e-6) and rp["fvd"]["value"] == pytest.approx(0.0, abs=1e-4)
    assert rp["lpips"]["value"] == pytest.approx(0.0, abs=1e-6)
    for m, v in rb.items():
        assert v["status"] == "ok", (m, v)
        if v["status"] == "ok":
            better = rp[m]["value"] > v["value"] if v["higher_is_better"] else rp[m]["value"] < v["value"]
            assert better, m


def test_protocol_resize_must_match_the_extractor():
    from skyeyes_bench.evaluate import check_extractors
    from skyeyes_bench.protocol import load_protocol

    p = load_protocol("synthtown@1")
    check_extractors(p)  # the shipped protocol agrees with its extractors
    bad = p.__class__(**{**p.__dict__, "metrics": tuple(
        m.__class__(**{**m.__dict__, "resize": "legacy-tf-bilinear"}) if m.name == "fid" else m
        for m in p.metrics)})
    with pytest.raises(UserError, match="metrics.fid.resize"):
        check_extractors(bad)


@pytest.mark.parametrize("tty", [False, True])
def test_progress_bars_only_on_a_terminal(tiny, scored, tmp_path, tty):
    """Without --quiet, bars are drawn only when stderr is a terminal: logs stay readable."""
    blur = scored[1]["b1"]
    _, _, err = run_cli("evaluate", "--allow-missing", str(blur), "--data", str(tiny), "--out", str(tmp_path / "r.json"), tty=tty)
    assert ("per-frame metrics" in err) == tty, err


# --------------------------------------------------------------------------- scene clusters


@pytest.fixture(scope="module")
def scene_scored(tmp_path_factory):
    """evalscene@1 (cluster = "scene"): blurs 0.7 and 1.5 on a 5-scene and a 2-scene dataset."""
    tmp = tmp_path_factory.mktemp("scene")
    with protocol_env(tmp, SCENE_PROTOCOL):
        for k in (5, 2):
            root = make_dataset(tmp / f"ds{k}", protocol="evalscene@1", scenes=k, seqs=2, frames=4, seed=k)
            ds = open_dataset(root)
            for name, sigma in (("b1", 0.7), ("b2", 1.5)):
                sub = blurred_submission(ds, tmp / f"{name}-{k}", sigma=sigma, method=name)
                evaluate(sub, data=root, out=tmp / f"{name}-{k}.json", progress=False)
        yield tmp


def test_scene_clusters_group_frames_by_lane(scene_scored):
    from skyeyes_bench import stats

    res, feats = read_results(scene_scored / "b1-5.json", features=True)
    st = res["statistics"]
    lanes = [f"test-0-lane{i:02d}" for i in range(5)]
    assert st["cluster"] == "scene" and st["clusters"] == 5 and st["cluster_ids"] == lanes
    assert len(res["dataset"]["sequences"]) == 10
    counts = stats.replicate_counts(5, 200, 0)  # depends only on (seed, resamples, clusters)
    for r in (0, 17, 199):
        chosen = {lanes[i] for i in np.flatnonzero(counts[r])}
        assert len(chosen) == 2
        # slow reference: SSIM over every frame whose scene (lane) was drawn
        want = np.mean([f["ssim"] for f in res["frames"] if f["scene"] in chosen])
        assert res["metrics"]["ssim"]["replicates"][r] == pytest.approx(want, rel=1e-5)
        x = feats["random-image-64"]
        rows = np.array([res["dataset"]["sequences"][q].split("/")[0] in chosen for q in x["seq"]])
        assert res["metrics"]["fid"]["replicates"][r] == pytest.approx(scipy_fid(x["sub"][rows], x["gt"][rows]), rel=1e-4)
    for m, v in res["metrics"].items():
        if v["status"] == "ok":
            assert v["interval"][0] <= v["value"] <= v["interval"][1], m
    assert res["metrics"]["fid"]["interval"][0] >= 0 and res["metrics"]["fvd"]["interval"][0] >= 0  # FID >= 0


def test_too_few_scenes_in_results_and_compare(scene_scored, tmp_path):
    res, _ = read_results(scene_scored / "b1-2.json")
    assert res["statistics"]["clusters"] == 2 and res["statistics"]["too_few"] == "too few scenes (K=2)"
    for m, v in res["metrics"].items():
        if v["status"] == "ok":
            assert isinstance(v["value"], float), m  # the point estimate stays
            assert v["interval"] is None and v["interval_note"] == "too few scenes (K=2)" and v["replicates"] is None
    rc, text, err = run_cli("compare", str(scene_scored / "b1-2.json"), str(scene_scored / "b2-2.json"))
    assert "too few scenes (K=2)" in text and "[" not in text.split("\n", 3)[-1]  # no interval printed
    rc, out, err = run_cli("compare", str(scene_scored / "b1-2.json"), str(scene_scored / "b2-2.json"), "--json")
    cmp = json.loads(out)
    assert cmp["cluster"] == "scene" and cmp["clusters"] == 2 and cmp["too_few"] == "too few scenes (K=2)"
    for m in ("psnr", "ssim", "fid", "kvd"):
        r = cmp["metrics"][m]
        assert r["bootstrap_interval"] is None and r["p_a_better_bootstrap"] is None and r["bayes"]["p_a_better"] is None
        assert r["advantage"] == (r["a"] - r["b"] if r["higher_is_better"] else r["b"] - r["a"])


def _parse(text):
    rows = {}
    for ln in text.splitlines():
        p = ln.split()
        if len(p) > 6 and p[1] == "A" and p[3] == "B" and p[5] == "advantage":
            rows[p[0]] = (p[2], p[4], p[6])
    return rows


def test_compare_prints_one_estimand(scene_scored, tmp_path):
    """A, B are the values evaluate reported; the printed advantage is the difference of the
    printed A and B; the interval comes from the stored replicates (no sidecars needed)."""
    a, _ = read_results(scene_scored / "b1-5.json")
    b, _ = read_results(scene_scored / "b2-5.json")
    rc, text, err = run_cli("compare", str(scene_scored / "b1-5.json"), str(scene_scored / "b2-5.json"))
    rows = _parse(text)
    assert set(rows) >= {"psnr", "ssim", "fid", "kid", "fvd", "kvd"}
    for m, (ta, tb, td) in rows.items():
        dec = len(td.split(".")[1]) if "." in td else 0
        assert len(ta.split(".")[1]) == len(tb.split(".")[1]) == dec
        want = float(ta) - float(tb) if a["metrics"][m]["higher_is_better"] else float(tb) - float(ta)
        assert float(td) == pytest.approx(want, abs=0.5 * 10**-dec), m
        assert float(ta) == pytest.approx(a["metrics"][m]["value"], abs=10**-dec)  # the evaluate value
        assert float(tb) == pytest.approx(b["metrics"][m]["value"], abs=10**-dec)
    assert "Student-t mu" in text
    # set metrics from the stored replicates alone: copy the JSON without the sidecars
    for n in ("b1", "b2"):
        shutil.copy(scene_scored / f"{n}-5.json", tmp_path)
    rc, out, err = run_cli("compare", str(tmp_path / "b1-5.json"), str(tmp_path / "b2-5.json"), "--json")
    cmp = json.loads(out)
    rc, out2, err = run_cli("compare", str(scene_scored / "b1-5.json"), str(scene_scored / "b2-5.json"), "--json")
    with_feats = json.loads(out2)
    for m in ("fid", "kid"):
        lo, hi = cmp["metrics"][m]["bootstrap_interval"]
        assert lo <= cmp["metrics"][m]["advantage"] <= hi
        assert [lo, hi] == pytest.approx(with_feats["metrics"][m]["bootstrap_interval"], rel=1e-4)
    # a submission compared with itself: zero difference in every replicate
    rc, out, err = run_cli("compare", str(tmp_path / "b1-5.json"), str(tmp_path / "b1-5.json"), "--json")
    for m, r in json.loads(out)["metrics"].items():
        if r["status"] == "ok":
            assert r["advantage"] == 0 and r["bootstrap_interval"] == [0.0, 0.0], m


def test_compare_recomputes_set_metric_replicates_from_the_sidecars(scene_scored, tmp_path):
    """Results without stored replicates (older files) but with their features sidecars: the
    set metrics' replicates are recomputed from the features, to the stored ones' interval (those
    are rounded to 6 digits). And the comparison names its methods, estimand and skipped metrics."""
    from skyeyes_bench import stats

    for n in ("b1", "b2"):
        doc = json.loads((scene_scored / f"{n}-5.json").read_text())
        for m in ("fid", "kid", "fvd", "kvd"):
            assert doc["metrics"][m].pop("replicates")
        (tmp_path / f"{n}-5.json").write_text(json.dumps(doc))
        shutil.copy(scene_scored / f"{n}-5.features.npz", tmp_path)
    a, fa = read_results(tmp_path / "b1-5.json", features=True)
    b, fb = read_results(tmp_path / "b2-5.json", features=True)
    got = comparison.compare_results(a, b, fa, fb, emcee_steps=200)
    stored = comparison.compare_results(*(read_results(scene_scored / f"{n}-5.json")[0] for n in ("b1", "b2")),
                                   emcee_steps=200)
    for m in ("fid", "kid", "fvd", "kvd"):
        assert got["metrics"][m]["bootstrap_interval"] == pytest.approx(stored["metrics"][m]["bootstrap_interval"],
                                                                        rel=1e-4), m
        assert got["metrics"][m]["bootstrap_interval"][0] < got["metrics"][m]["bootstrap_interval"][1]
    # without replicates or sidecars: the set metrics are reported, not resampled
    bare = comparison.compare_results(a, b, None, None, emcee_steps=200)
    assert bare["metrics"]["fid"]["status"] == "skipped" and "no replicates" in bare["metrics"]["fid"]["note"]
    assert (got["a"], got["b"]) == ("b1", "b2") and got["estimand"] == comparison.COMPARE_ESTIMAND
    # a metric unavailable on one side is skipped, naming the side
    b_lp = json.loads(json.dumps(b))
    b_lp["metrics"]["psnr"]["status"] = "unavailable"
    assert comparison.compare_results(a, b_lp, emcee_steps=200)["metrics"]["psnr"]["note"] == "psnr unavailable in B"
    assert comparison.compare_results(b_lp, a, emcee_steps=200)["metrics"]["psnr"]["note"] == "psnr unavailable in A"


def test_results_record_what_was_scored(scored):
    """The results document's provenance, recomputed from the files: tool, frame count and sizes
    of the ground truth, the submission's absolute path and manifest fields, and the sha256 over
    its frames ("<scene>/<file> <sha256 of the file>\\n" lines, sorted)."""
    import hashlib

    from PIL import Image

    import skyeyes_bench

    ds, subs, res, _ = scored
    doc, sub = res["b1"], subs["b1"]
    assert doc["tool"] == {"name": "skyeyes-bench", "version": skyeyes_bench.__version__}
    pngs = sorted(p for p in Path(subs["gt"]).rglob("*.png"))  # the ground truth, written as a submission
    assert doc["dataset"]["frames"] == len(pngs) == 96
    assert doc["dataset"]["resolution"] == sorted({"{}x{}".format(*Image.open(p).size) for p in pngs})
    assert doc["submission"]["path"] == str(Path(sub).resolve())
    manifest = json.loads((Path(sub) / "submission.json").read_text())
    for k in ("method", "peak_memory_mb", "hardware", "timings"):
        assert k in doc["submission"] and doc["submission"][k] == manifest.get(k), k
    lines = sorted(f"{p.relative_to(sub).as_posix()} {hashlib.sha256(p.read_bytes()).hexdigest()}\n"
                   for p in Path(sub).rglob("*.png"))
    assert len(lines) == 96
    assert doc["submission"]["frames_sha256"] == hashlib.sha256("".join(lines).encode()).hexdigest()


def test_missing_extractor_weights_make_only_their_metrics_unavailable(tmp_path, monkeypatch):
    """FID and KID on Inception with no weights in the cache: both unavailable, saying why and
    what fixes it; the extractor marked unavailable; FVD and KVD (another extractor) still scored."""
    from builders.evaluation import TEST_PROTOCOL, install_test_protocol

    text = TEST_PROTOCOL
    for m in ("fid", "kid"):
        text = text.replace(f'[metrics.{m}]\nextractor = "random-image-64"\nresize = "none"',
                            f'[metrics.{m}]\nextractor = "inception-tf-2015"\nresize = "clean-bicubic"')
    assert text.count("inception-tf-2015") == 2
    install_test_protocol(tmp_path, monkeypatch, text)
    root = make_dataset(tmp_path / "ds", scenes=1, seqs=2, frames=8)
    ds = open_dataset(root)
    res = evaluate(blurred_submission(ds, tmp_path / "sub", sigma=1.0), data=root, out=tmp_path / "r.json",
                   progress=False)
    for m in ("fid", "kid"):
        r = res["metrics"][m]
        assert r["status"] == "unavailable" and "weights" in r["reason"] and "weights fetch" in r["fix"], r
    assert res["extractors"]["inception-tf-2015"]["status"] == "unavailable"
    assert res["extractors"]["random-video-64"]["status"] == "ok"
    # LPIPS (a frame metric's network, no weights here either): the metric and its network
    assert res["metrics"]["lpips"]["status"] == "unavailable"
    assert res["extractors"]["lpips-alex-v0.1"]["status"] == "unavailable"
    assert res["metrics"]["fvd"]["status"] == res["metrics"]["kvd"]["status"] == "ok"
