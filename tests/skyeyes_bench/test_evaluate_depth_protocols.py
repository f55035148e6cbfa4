"""carla-town04@2 and citysample-region5@2 end to end: a capture with ground and aerial depth
(builders.depth_captures) through the importer, a submission scored under v1 and v2. v2 scores
v1's data: the dataset says @1, v1 submissions are scored by both, v2's v1 metrics are v1's, and
the depth metrics are there and finite. New submissions say the latest version, v3 (v2 plus
FID∞ and FVD∞), which scores the same data."""

import json
import math
import shutil

import numpy as np
import pytest
from builders.depth_captures import make_carla_depth, make_matrixcity_depth
from builders.evaluation import ROOT, blurred_submission
from builders.weights import require

from skyeyes_bench import imagefiles
from skyeyes_bench.data.importers import import_carla, import_matrixcity
from skyeyes_bench.data.layout import open_dataset
from skyeyes_bench.evaluate import evaluate
from skyeyes_bench.metricspec import SEQUENCE_METRICS
from skyeyes_bench.protocol import current_for_data, load_protocol, load_protocol_file
from skyeyes_bench.submission import write_template

V1_METRICS = ["psnr", "ssim", "lpips", "fid", "kid", "fvd", "kvd"]
V3_METRICS = ["fid_inf", "fvd_inf"]  # what v3 adds to v2
#: sha256 of the v1 files: adding v2 must leave them (and results filed with them) as they were.
V1_SHA256 = {"carla-town04": "9c3a751b6c19792c32fd4a9ec478a8c5db63afb7f335a8f3109a31f30c038262",
             "citysample-region5": "02c9056c4cb57ee56328d8b97594d2f7af9dcdd16bbf69b28abd148325b2c4c6"}


def _import(source, tmp):
    if source == "carla":
        truth = make_carla_depth(tmp / "capture")
        out, _ = import_carla(tmp / "capture", tmp / "data", progress=False)
        return out, {str(tmp / "capture" / k): v for k, v in truth.items()}
    src, truth = make_matrixcity_depth(tmp / "capture")
    out, _, _ = import_matrixcity(src, tmp / "data", town="region5", progress=False)
    return out, truth


@pytest.fixture(scope="module", params=[("carla", "carla-town04"), ("matrixcity", "citysample-region5")],
                ids=["carla", "citysample"])
def scored(request, tmp_path_factory):
    """The imported dataset and results of one blurred submission: written now (v3, the latest),
    the same frames as a v1 submission scored by v1 and by v2, and the ground truth (v3)."""
    from skyeyes_bench.metrics.extractors import get_extractor

    source, pid = request.param
    tmp = tmp_path_factory.mktemp(source)
    mp = pytest.MonkeyPatch()
    try:
        mp.setenv("SKYEYES_CACHE", str(tmp / "cache"))
        # LPIPS weights only: Inception and I3D would take most of the time, and the set metrics
        # come from features that do not depend on the depth metrics (without those weights
        # FID/KID/FVD/KVD are `unavailable`, the same in both versions).
        require(*get_extractor("lpips-alex-v0.1").files)
        data, truth = _import(source, tmp)
        ds = open_dataset(data)
        new = blurred_submission(ds, tmp / "new", sigma=1.0)
        old = tmp / "old"  # the same frames as written before v2 existed
        shutil.copytree(new, old)
        man = json.loads((old / "submission.json").read_text())
        man.update(protocol=f"{pid}@1", protocol_sha256=load_protocol(f"{pid}@1").sha256)
        (old / "submission.json").write_text(json.dumps(man))
        gt = write_template(ds, tmp / "gt", from_ground_truth=True)
        res = {"new": evaluate(new, data=data, progress=False),
               "v1": evaluate(old, data=data, progress=False),
               "v1 as v2": evaluate(old, data=data, protocol=f"{pid}@2", progress=False),
               "gt": evaluate(gt, data=data, progress=False)}
        yield pid, ds, truth, res
    finally:
        mp.undo()


def test_v2_is_v1_plus_the_depth_metrics_and_v1_is_unchanged(scored):
    import dataclasses

    pid = scored[0]
    v1 = load_protocol_file(ROOT / "protocols" / pid / "v1.toml")
    v2 = load_protocol_file(ROOT / "protocols" / pid / "v2.toml")
    assert v1.sha256 == V1_SHA256[pid] and "dataset_protocol" not in v1.to_dict()["data"]
    assert v2.data_ref == f"{pid}@1" and dataclasses.replace(v2.data, dataset_protocol="") == v1.data
    assert v2.capture == v1.capture and v2.statistics == v1.statistics
    assert v2.metrics[:len(v1.metrics)] == v1.metrics
    assert [m.name for m in v2.metrics[len(v1.metrics):]] == list(SEQUENCE_METRICS)
    assert {m.depth_tolerance for m in v2.metrics[len(v1.metrics):]} == {0.01}
    # v3: v2 and FID∞ / FVD∞ on FID's and FVD's features; the latest, so new submissions say it
    v3 = load_protocol_file(ROOT / "protocols" / pid / "v3.toml")
    assert v3.data == v2.data and v3.capture == v2.capture and v3.statistics == v2.statistics
    assert v3.metrics[:len(v2.metrics)] == v2.metrics and [m.name for m in v3.metrics[len(v2.metrics):]] == V3_METRICS
    assert v3.metric("fid_inf").extractor == v3.metric("fid").extractor
    assert (v3.metric("fvd_inf").extractor, v3.metric("fvd_inf").clip_length, v3.metric("fvd_inf").clip_stride) == (
        v3.metric("fvd").extractor, v3.metric("fvd").clip_length, v3.metric("fvd").clip_stride)
    assert load_protocol(pid).ref == f"{pid}@3" and current_for_data(f"{pid}@1") == f"{pid}@3"


def test_importer_writes_v1_data_with_ground_and_aerial_depth(scored):
    pid, ds, truth, _ = scored
    assert ds.protocol == f"{pid}@1"  # imported with the default --protocol, the latest (v3)
    for name in ds.splits["test"]:
        scene = ds.scenes[name]
        assert scene.layers()["ground_depth"] and scene.layers()["aerial_depth"] and scene.aerial
        for frame in [*scene.aerial, *scene.ground]:
            rgb, cam = imagefiles.read_image_uint8(frame.path), frame.camera()
            t = next(v for v in truth.values() if np.allclose(v["camera"].c2w, cam.c2w, atol=1e-9)
                     and np.array_equal(v["rgb"], rgb))  # the view it was rendered from, same pixels
            d = frame.depth()
            assert np.array_equal(np.isinf(d), np.isinf(t["depth"]))
            # CARLA's 24-bit code: 6e-5 m steps; MatrixCity's float16 street depth: 2^-11 relative
            np.testing.assert_allclose(d[np.isfinite(d)], t["depth"][np.isfinite(d)], rtol=5e-4, atol=1e-4)
            np.testing.assert_allclose(cam.K, t["camera"].K, rtol=1e-12)


def test_new_submissions_say_the_latest_and_old_ones_are_scored_by_both(scored):
    pid, _, _, res = scored
    assert res["new"]["protocol"]["ref"] == f"{pid}@3" and res["new"]["submission"]["protocol"] == f"{pid}@3"
    assert res["v1"]["protocol"]["ref"] == f"{pid}@1" and list(res["v1"]["metrics"]) == V1_METRICS
    assert res["v1 as v2"]["protocol"]["ref"] == f"{pid}@2" and res["v1 as v2"]["submission"]["protocol"] == f"{pid}@1"
    assert list(res["v1 as v2"]["metrics"]) == V1_METRICS + list(SEQUENCE_METRICS)
    assert list(res["new"]["metrics"]) == V1_METRICS + list(SEQUENCE_METRICS) + V3_METRICS
    assert res["v1 as v2"]["metrics"] == {k: res["new"]["metrics"][k] for k in res["v1 as v2"]["metrics"]}
    # no Inception weights and no 16-frame clips here: FID∞ and FVD∞ are unavailable where FID and FVD are
    for name in V3_METRICS:
        assert res["new"]["metrics"][name]["status"] == "unavailable" == res["new"]["metrics"][name[:3]]["status"]


def test_v1_metrics_of_v2_equal_v1(scored):
    _, _, _, res = scored
    v1, v2 = res["v1"], res["new"]
    for name in V1_METRICS:
        assert v2["metrics"][name] == v1["metrics"][name], name
    assert [v2["metrics"][n]["status"] for n in V1_METRICS] == ["ok"] * 3 + ["unavailable"] * 4
    for a, b in zip(v1["frames"], v2["frames"], strict=True):
        assert {k: b[k] for k in a} == a  # v2's records: v1's fields unchanged, plus the depth metrics
    for sid, seq in v1["sequences"].items():
        assert {k: v2["sequences"][sid][k] for k in seq} == seq


def test_depth_metrics_present_and_finite(scored):
    _, ds, _, res = scored
    m = res["new"]["metrics"]
    for name in SEQUENCE_METRICS:
        assert m[name]["status"] == "ok" and math.isfinite(m[name]["value"]), (name, m[name])
    share = m["unseen_share"]["value"]
    assert 0.5 < share < 0.95 and m["unseen_share"]["reference"] and m["warp_floor"]["reference"]
    n_px = sum(f.width * f.height for name in ds.splits["test"] for f in ds.scenes[name].ground)
    assert m["psnr_seen"]["pixels"] + m["psnr_unseen"]["pixels"] == n_px
    assert m["psnr_unseen"]["pixels"] / n_px == pytest.approx(share, rel=1e-12)
    # blurred frames: near the floor (blur keeps the geometry; it can even go below the floor of
    # these aliased frames, docs/metrics.md "Caveat")
    assert 0 < m["warp_floor"]["value"] < 0.1 and 0 < m["warp"]["value"] < 0.1
    # the ground truth: exact on both regions, its warp error the floor; the data's share
    g = res["gt"]["metrics"]
    assert g["psnr_seen"]["value"] == math.inf and g["psnr_unseen"]["value"] == math.inf
    assert g["ssim_seen"]["value"] == pytest.approx(1.0, abs=1e-12)
    assert g["lpips_unseen"]["value"] == pytest.approx(0.0, abs=1e-6)
    assert g["warp"]["value"] == g["warp_floor"]["value"] == m["warp_floor"]["value"]
    assert g["unseen_share"]["value"] == share
