"""Protocol files: validation messages, versions, canonical hash, `protocols list|show`."""

import hashlib
import json
import re
import shutil
import tomllib
from pathlib import Path

import pytest
from conftest import ROOT, run_cli

from skyeyes_bench.errors import UserError
from skyeyes_bench.metricspec import SEQUENCE_METRICS
from skyeyes_bench.protocol import list_protocols, load_protocol, load_protocol_file

V1 = ROOT / "protocols" / "synthtown" / "v1.toml"


@pytest.fixture
def protos(tmp_path, monkeypatch) -> Path:
    """A private protocols folder (SKYEYES_PROTOCOLS) holding a copy of synthtown v1."""
    root = tmp_path / "protocols"
    (root / "synthtown").mkdir(parents=True)
    shutil.copy(V1, root / "synthtown" / "v1.toml")
    monkeypatch.setenv("SKYEYES_PROTOCOLS", str(root))
    return root


def _edit(text: str, old: str, new: str) -> str:
    assert text.count(old) == 1, old
    return text.replace(old, new)


def _write_variant(protos: Path, old: str, new: str) -> Path:
    f = protos / "synthtown" / "v1.toml"
    f.write_text(_edit(f.read_text(), old, new))
    return f


@pytest.mark.parametrize(
    "old, new, expect",
    [
        ("seed = 0\n", "seed = 0\nseeds = 3\n", "unknown key 'statistics.seeds'"),
        ('title = "', 'colour = "red"\ntitle = "', "unknown key 'colour'"),
        ("[metrics.psnr]\n", "[metrics.psnr]\nextractor = \"x\"\n", "unknown key 'metrics.psnr.extractor'"),
        ("[metrics.psnr]\n", "[metrics.psnrr]\n", "unknown metric 'metrics.psnrr'"),
        ("width = 128\n", "width = \"128\"\n", "key 'data.width' must be int"),
        ("width = 128\n", "width = 128.0\n", "key 'data.width' must be int"),
        ("fov_deg = 90.0\n", "fov_deg = true\n", "key 'data.fov_deg' must be float"),
        ("clip_length = 16\nclip_stride = 16\n\n[metrics.kvd]", "clip_length = \"16\"\nclip_stride = 16\n\n[metrics.kvd]",
         "key 'metrics.fvd.clip_length' must be int"),
        ("yaws_deg = [0.0,", "yaws_deg = [\"a\",", "key 'capture.yaws_deg' must be tuple[float"),
        ("emcee_walkers = 32\n", "", "missing key 'statistics.emcee_walkers'"),
        ("ground_step_m = 2.0\n", "", "missing key 'capture.ground_step_m'"),
        ('reference = "', 'referencee = "', "unknown key 'referencee'"),
        ("version = 1\n", "version = 0\n", "key 'version' must be an int >= 1"),
        ("interval = 0.95\n", "interval = 1.5\n", "key 'statistics.interval' must lie in (0, 1)"),
        ("emcee_burn = 1000\n", "emcee_burn = 5000\n", "key 'statistics.emcee_burn'"),
        ('extractor = "lpips-alex-v0.1"\n', "", "missing key 'metrics.lpips.extractor'"),
        ('cluster = "sequence"\n', 'cluster = "lane"\n',
         "key 'statistics.cluster' must be one of 'scene', 'sequence', got 'lane'"),
    ],
)
def test_bad_protocol_names_file_and_key(protos, old, new, expect):
    f = _write_variant(protos, old, new)
    with pytest.raises(UserError) as e:
        load_protocol("synthtown@1")
    msg = str(e.value)
    assert str(f) in msg and expect in msg, msg
    assert "\n" not in msg
    # Through the CLI: one line on stderr, exit 2, no traceback.
    rc, out, err = run_cli("protocols", "show", "synthtown", check=2)
    assert expect in err and str(f) in err
    assert "Traceback" not in err and err.count("\n") == 1


def test_missing_table_and_bad_toml(protos):
    f = protos / "synthtown" / "v1.toml"
    text = f.read_text()
    f.write_text(text.split("[statistics]")[0])
    with pytest.raises(UserError, match=r"v1\.toml: missing table \[statistics\]"):
        load_protocol("synthtown")
    f.write_text(text + "\n[data\n")
    with pytest.raises(UserError, match=r"v1\.toml: not valid TOML"):
        load_protocol("synthtown")


def test_id_and_version_must_match_path(protos):
    (protos / "synthtown" / "v2.toml").write_text(V1.read_text())  # says version = 1
    with pytest.raises(UserError, match=r"v2\.toml: file says id='synthtown' version=1"):
        load_protocol("synthtown@2")


def test_latest_version_when_omitted(protos):
    v2 = _edit(V1.read_text(), "version = 1\n", "version = 2\n")
    v2 = _edit(v2, "bootstrap_resamples = 1000\n", "bootstrap_resamples = 2000\n")
    (protos / "synthtown" / "v2.toml").write_text(v2)
    assert load_protocol("synthtown").version == 2
    assert load_protocol("synthtown").statistics.bootstrap_resamples == 2000
    assert load_protocol("synthtown@1").statistics.bootstrap_resamples == 1000
    assert load_protocol("synthtown@2").ref == "synthtown@2"
    with pytest.raises(UserError, match="has no version 3; versions: 1, 2"):
        load_protocol("synthtown@3")
    with pytest.raises(UserError, match="unknown protocol 'nope'; known: synthtown"):
        load_protocol("nope")
    with pytest.raises(UserError, match="expected 'ID' or 'ID@N'"):
        load_protocol("synthtown@x")
    # v01.toml is not a version file (would alias v1)
    (protos / "synthtown" / "v01.toml").write_text(V1.read_text())
    assert [p.ref for p in list_protocols()] == ["synthtown@1", "synthtown@2"]


def _independent_sha(path: Path) -> str:
    """sha256 computed here from tomllib + json, not through the code under test."""
    raw = tomllib.loads(path.read_text())
    floats = {"fov_deg", "ground_height_m", "ground_pitch_deg", "ground_step_m", "aerial_height_m",
              "aerial_pitch_deg", "sigma", "k1", "k2", "interval"}

    def norm(d):
        return {k: (norm(v) if isinstance(v, dict) else
                    float(v) if k in floats else [float(x) for x in v] if k == "yaws_deg" else v)
                for k, v in d.items()}

    raw = norm(raw)
    blob = json.dumps(raw, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(blob.encode()).hexdigest()


def test_sha256_stable_under_reformatting_changed_by_values(protos):
    f = protos / "synthtown" / "v1.toml"
    base = load_protocol_file(f).sha256
    assert base == _independent_sha(f)
    # Comments, blank lines, key order, spacing, int-vs-float spelling of a float: same hash.
    text = f.read_text()
    spaced = re.sub(r"^(\w+) = ", r"\1   =   ", text, flags=re.M)
    reformatted = "# a comment\n\n" + spaced.replace("\n[", "\n\n# hi\n[")
    reformatted = _edit(reformatted, "fov_deg   =   90.0", "fov_deg = 90  # degrees")
    reformatted = _edit(reformatted, "seed   =   0\ncluster   =   \"sequence\"",
                        "cluster = 'sequence'\nseed = 0")
    f.write_text(reformatted)
    assert load_protocol_file(f).sha256 == base
    # Any value change: a different hash.
    for old, new in [("seed   =   0", "seed = 1"), ("fov_deg   =   90.0", "fov_deg = 90.5"),
                     ("k2   =   0.03", "k2 = 0.031"), ('cluster   =   "sequence"', 'cluster = "scene"')]:
        f.write_text(_edit(spaced, old, new))
        assert load_protocol_file(f).sha256 != base, new
        assert load_protocol_file(f).sha256 == _independent_sha(f)


def test_repository_protocols_load():
    refs = {p.ref: p for p in list_protocols(ROOT / "protocols")}
    assert set(refs) >= {"carla-town04@1", "carla-town04@2", "citysample-region5@1", "citysample-region5@2",
                         "synthtown@1"}
    carla, city = refs["carla-town04@1"], refs["citysample-region5@1"]
    assert carla.data.test == ("Town04",) and carla.data.train == ("Town01", "Town02", "Town03", "Town05")
    assert city.data.test == ("region5",) and set(city.data.train) == {"region1", "region2", "region3", "region4", "region6"}
    assert carla.capture.aerial_height_m == 52.0 and city.capture.aerial_height_m == 100.0
    for p in refs.values():
        assert p.capture.yaws_deg == tuple(45.0 * k for k in range(8))
        assert p.capture.ground_height_m == 2.0 and p.capture.ground_step_m == 2.0
        assert p.capture.aerial_pitch_deg == -45.0 and p.capture.ground_pitch_deg == 0.0
        assert p.metric("fvd").clip_length == 16
        base = {"psnr", "ssim", "lpips", "fid", "kid", "fvd", "kvd"}
        # the versions that score an earlier one's data with the depth-based metrics too, and then FID∞ / FVD∞
        inf = p.ref in ("synthtown@4", "carla-town04@3", "citysample-region5@3")
        depth = inf or p.ref in ("synthtown@3", "carla-town04@2", "citysample-region5@2", "synthtown-stiff@1")
        want = (base | set(SEQUENCE_METRICS) if depth else base) | ({"fid_inf", "fvd_inf"} if inf else set())
        assert set(p.metric_names) == want
    assert (carla.data.width, carla.data.height) == (512, 512) == (city.data.width, city.data.height)


def test_synthtown_v3_is_v2_plus_the_depth_metrics():
    import dataclasses

    v2 = load_protocol_file(ROOT / "protocols" / "synthtown" / "v2.toml")
    v3 = load_protocol_file(ROOT / "protocols" / "synthtown" / "v3.toml")
    assert v3.data_ref == "synthtown@2" and v2.data_ref == "synthtown@2"
    assert dataclasses.replace(v3.data, dataset_protocol="") == v2.data
    assert v3.capture == v2.capture and v3.statistics == v2.statistics
    assert v3.metrics[:len(v2.metrics)] == v2.metrics
    assert {m.name for m in v3.metrics[len(v2.metrics):]} == set(SEQUENCE_METRICS)
    assert {m.depth_tolerance for m in v3.metrics[len(v2.metrics):]} == {0.01}
    assert v3.metric("lpips_seen").extractor == v3.metric("lpips").extractor
    # v1 and v2 keep their sha256 (results filed with them stay comparable)
    assert v2.sha256 == "2f003448a43bfcabdbc9c74e0dee4bfd203ccc26e16a57df5f1bfa05b09f68f5"
    assert "dataset_protocol" not in v2.to_dict()["data"]


def test_current_protocol_for_data_and_dataset_protocol_checks(protos):
    from skyeyes_bench.protocol import current_for_data

    v1 = V1.read_text()
    (protos / "synthtown" / "v2.toml").write_text(_edit(v1, "version = 1\n", 'version = 2\n').replace(
        'width = ', 'dataset_protocol = "synthtown@1"\nwidth = ', 1))
    assert current_for_data("synthtown@1") == "synthtown@2" and load_protocol("synthtown@2").data_ref == "synthtown@1"
    assert current_for_data("other@4") == "other@4"
    for bad in ("synthtown@2", "synthtown", "x y@1"):
        (protos / "synthtown" / "v2.toml").write_text(_edit(v1, "version = 1\n", 'version = 2\n').replace(
            'width = ', f'dataset_protocol = "{bad}"\nwidth = ', 1))
        with pytest.raises(UserError, match="key 'data.dataset_protocol' must name another protocol"):
            load_protocol("synthtown@2")
    (protos / "synthtown" / "v2.toml").write_text(_edit(v1, "version = 1\n", 'version = 2\n') + (
        "\n[metrics.warp]\ndepth_tolerance = 1.5\n"))
    with pytest.raises(UserError, match=r"key 'metrics.warp.depth_tolerance' must lie in \(0, 1\)"):
        load_protocol("synthtown@2")


def test_protocols_list_and_show_cli(protos):
    v2 = _edit(V1.read_text(), "version = 1\n", "version = 2\n")
    (protos / "synthtown" / "v2.toml").write_text(_edit(v2, 'title = "SynthTown', 'title = "SynthTown v2'))
    _, out, _ = run_cli("protocols", "list")
    lines = out.splitlines()
    assert lines[0].startswith("synthtown@1\tSynthTown: procedural towns")
    assert lines[1].startswith("synthtown@2\tSynthTown v2")
    assert len(lines) == 2
    _, out, _ = run_cli("protocols", "show", "synthtown")
    p2 = load_protocol_file(protos / "synthtown" / "v2.toml")
    assert out.splitlines()[0] == f"# synthtown@2  sha256 {p2.sha256}"
    assert "[metrics.fvd]" in out and "clip_length = 16" in out and "interval = 0.95" in out
    _, out, _ = run_cli("protocols", "show", "synthtown@1", "--json")
    d = json.loads(out)
    assert d["ref"] == "synthtown@1" and d["sha256"] == _independent_sha(protos / "synthtown" / "v1.toml")
    assert d["metrics"]["ssim"] == {"aggregate": "mean", "window": 11, "sigma": 1.5, "k1": 0.01, "k2": 0.03}
    rc, _, err = run_cli("protocols", "show", "nope", check=2)
    assert err.startswith("skyeyes-bench: error: unknown protocol 'nope'")


def test_protocols_list_names_a_broken_file(protos):
    f = _write_variant(protos, "seed = 0\n", "seed = 0.5\n")
    rc, out, err = run_cli("protocols", "list", check=2)
    assert err.strip() == (f"skyeyes-bench: error: {f}: key 'statistics.seed' must be int, got 0.5")
