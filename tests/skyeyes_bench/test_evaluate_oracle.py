"""An evaluate-level oracle: everything `results.json` reports, recomputed by brute force from the
file itself (per-frame values) and its features sidecar, with slow code written out here: per-
sequence and per-cluster means, FID/FVD by scipy sqrtm, KID/KVD as explicit U-statistics over the
protocol's random subsets, every half-sampling replicate on materialised rows of BOTH sets, and
compare's paired interval from the two submissions' brute-force replicates."""

import json
import math

import numpy as np
import pytest
from builders.evaluation import SCENE_PROTOCOL, blurred_submission, make_dataset, protocol_env, scipy_fid
from conftest import run_cli

from skyeyes_bench import stats
from skyeyes_bench.data.layout import open_dataset
from skyeyes_bench.evaluate import evaluate, read_results

# evalscene@1 with subsets smaller than the sets, so the protocol's subset draw matters.
ORACLE_PROTOCOL = (SCENE_PROTOCOL.replace('id = "evalscene"', 'id = "evaloracle"')
                   .replace("subset_size = 100", "subset_size = 30").replace("subset_size = 20", "subset_size = 12"))
K_SCENES, SEQS, FRAMES = 5, 2, 8  # 80 frames, 20 clips of 4


@pytest.fixture(scope="module")
def oracle(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("oracle")
    with protocol_env(tmp, ORACLE_PROTOCOL):
        root = make_dataset(tmp / "ds", protocol="evaloracle@1", scenes=K_SCENES, seqs=SEQS, frames=FRAMES, seed=7)
        ds = open_dataset(root)
        for name, sigma in (("a", 0.6), ("b", 1.4)):
            sub = blurred_submission(ds, tmp / name, sigma=sigma, method=name)
            evaluate(sub, data=root, out=tmp / f"{name}.json", progress=False)
        yield tmp


def _protocol():
    import tomllib

    return tomllib.loads(ORACLE_PROTOCOL)


def _mmd_loops(x, y):
    """Unbiased MMD^2, polynomial kernel (x.y / d + 1)^3, as double sums over pairs."""
    d = x.shape[1]

    def k(a, b):
        return (a @ b / d + 1.0) ** 3

    n, m = len(x), len(y)
    sxx = sum(k(x[i], x[j]) for i in range(n) for j in range(n) if i != j) / (n * (n - 1))
    syy = sum(k(y[i], y[j]) for i in range(m) for j in range(m) if i != j) / (m * (m - 1))
    sxy = sum(k(x[i], y[j]) for i in range(n) for j in range(m)) / (n * m)
    return sxx + syy - 2 * sxy


def _kid_with_subsets(x, y, subset_size, num_subsets, seed):
    """The protocol's KID: num_subsets subsets of m = min(subset_size, n) rows drawn without
    replacement from each set (numpy default_rng(seed), x's draw then y's), averaged."""
    m = min(subset_size, len(x), len(y))
    rng = np.random.default_rng(seed)
    vals = []
    for _ in range(num_subsets):
        ix = rng.choice(len(x), m, replace=False)
        iy = rng.choice(len(y), m, replace=False)
        vals.append(_mmd_loops(x[ix], y[iy]))
    return float(np.mean(vals))


def _scene(seq_id):
    return seq_id.split("/")[0]


def _replicate_scenes(res):
    """For each replicate, the set of scene names it draws (K // 2 of K, without replacement)."""
    st = res["statistics"]
    k = st["clusters"]
    counts = stats.replicate_counts(k, st["resamples"], st["seed"])  # the protocol's draw design
    assert counts.shape == (st["resamples"], k) and (counts.sum(1) == k // 2).all()
    assert set(np.unique(counts)) <= {0.0, 1.0}
    return [frozenset(st["cluster_ids"][i] for i in np.flatnonzero(c)) for c in counts]


def test_per_sequence_values_are_means_of_their_frames(oracle):
    res, _ = read_results(oracle / "a.json")
    assert len(res["sequences"]) == K_SCENES * SEQS
    for sid, rec in res["sequences"].items():
        frames = [f for f in res["frames"] if res["dataset"]["sequences"][f["sequence"]] == sid]
        assert all(f["scene"] == _scene(sid) for f in frames)
        assert len(frames) == rec["frames"] == FRAMES
        ssim = sum(f["ssim"] for f in frames) / len(frames)
        assert rec["ssim"] == pytest.approx(ssim, rel=1e-9), sid
        mse = sum(10 ** (-f["psnr"] / 10) for f in frames) / len(frames)
        assert rec["psnr"] == pytest.approx(-10 * math.log10(mse), rel=1e-9), sid
    m = res["metrics"]
    assert m["ssim"]["value"] == pytest.approx(sum(f["ssim"] for f in res["frames"]) / len(res["frames"]), rel=1e-12)


def test_frame_metric_replicates_are_means_over_drawn_scenes(oracle):
    res, _ = read_results(oracle / "a.json")
    assert res["statistics"]["cluster"] == "scene" and res["statistics"]["clusters"] == K_SCENES
    for name in ("psnr", "ssim"):
        for r, chosen in enumerate(_replicate_scenes(res)):
            vals = [f[name] for f in res["frames"] if f["scene"] in chosen]
            assert len(vals) == (K_SCENES // 2) * SEQS * FRAMES
            assert res["metrics"][name]["replicates"][r] == pytest.approx(sum(vals) / len(vals), rel=1e-5), (name, r)


@pytest.mark.parametrize("name, extractor", [("fid", "random-image-64"), ("fvd", "random-video-64"),
                                             ("kid", "random-image-64"), ("kvd", "random-video-64")])
def test_set_metrics_and_their_replicates_by_brute_force(oracle, name, extractor):
    res, feats = read_results(oracle / "a.json", features=True)
    f = feats[extractor]
    x, y = np.asarray(f["sub"], np.float64), np.asarray(f["gt"], np.float64)
    scenes = np.array([_scene(res["dataset"]["sequences"][q]) for q in f["seq"]])
    assert len(x) == len(y) == K_SCENES * SEQS * (FRAMES if name in ("fid", "kid") else FRAMES // 4)
    spec = _protocol()["metrics"][name]
    value = res["metrics"][name]["value"]
    if name in ("fid", "fvd"):
        assert value == pytest.approx(scipy_fid(x, y), rel=1e-6)
    else:
        want = _kid_with_subsets(x, y, spec["subset_size"], spec["num_subsets"], _protocol()["statistics"]["seed"])
        assert value == pytest.approx(want, rel=1e-9, abs=1e-12)
        assert min(spec["subset_size"], len(x)) < len(x)  # the subsets are proper subsets here
    # Each replicate: the metric on the rows of the drawn scenes, in both sets (paired), full sample.
    cache = {}
    for r, chosen in enumerate(_replicate_scenes(res)):
        if chosen not in cache:
            rows = np.isin(scenes, list(chosen))
            cache[chosen] = scipy_fid(x[rows], y[rows]) if name in ("fid", "fvd") else _mmd_loops(x[rows], y[rows])
        assert res["metrics"][name]["replicates"][r] == pytest.approx(cache[chosen], rel=1e-5, abs=1e-9), (name, r)
    assert len(cache) == math.comb(K_SCENES, K_SCENES // 2)


def _interval(estimate, replicates, level, k):
    """Half-sampling interval written out: draws est - sqrt(m/(k-m)) (theta_r - est), their
    inverted-CDF percentile interval, widened to contain est."""
    m = k // 2
    s = math.sqrt(m / (k - m))
    d = np.sort([estimate - s * (t - estimate) for t in replicates])
    a = (1 - level) / 2
    lo = d[max(int(math.ceil(a * len(d))) - 1, 0)]
    hi = d[max(int(math.ceil((1 - a) * len(d))) - 1, 0)]
    return min(lo, estimate), max(hi, estimate)


def test_compare_paired_interval_from_brute_force_replicates(oracle):
    """compare's advantage interval: per replicate, B - A (lower is better) of the SAME drawn
    scenes, both recomputed from the sidecars by brute force."""
    a, fa = read_results(oracle / "a.json", features=True)
    b, fb = read_results(oracle / "b.json", features=True)
    rc, out, err = run_cli("compare", str(oracle / "a.json"), str(oracle / "b.json"), "--json")
    cmp = json.loads(out)
    level = _protocol()["statistics"]["interval"]
    draws = _replicate_scenes(a)
    for name, ex in (("kid", "random-image-64"), ("fvd", "random-video-64")):
        per = []
        for f, res in ((fa[ex], a), (fb[ex], b)):
            x, y = np.asarray(f["sub"], np.float64), np.asarray(f["gt"], np.float64)
            scenes = np.array([_scene(res["dataset"]["sequences"][q]) for q in f["seq"]])
            vals = {}
            for chosen in set(draws):
                rows = np.isin(scenes, list(chosen))
                vals[chosen] = scipy_fid(x[rows], y[rows]) if name == "fvd" else _mmd_loops(x[rows], y[rows])
            per.append(np.array([vals[c] for c in draws]))
        adv = b["metrics"][name]["value"] - a["metrics"][name]["value"]
        r = cmp["metrics"][name]
        assert r["advantage"] == pytest.approx(adv, rel=1e-12)
        want = _interval(adv, per[1] - per[0], level, K_SCENES)
        assert r["bootstrap_interval"] == pytest.approx(list(want), rel=1e-4, abs=1e-9), name
        assert adv > 0  # less blur is better
