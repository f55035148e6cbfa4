"""capture-carla's live path: against a fake `carla` module (builders.carla_capture: images a
known function of the sensor transform; injected time-outs and a server that goes away), against
the real carla package without a server (an OpenDRIVE map), and against a real CARLA server when
one is reachable (SKYEYES_CARLA=host:port, default localhost:2000; skipped otherwise)."""

import json
import os
import socket
import sys

import numpy as np
import pytest
from builders.carla_capture import expected_pixels, fake_carla, waypoints_json
from conftest import run_cli

from skyeyes_bench import imagefiles
from skyeyes_bench.data.layout import open_dataset

TINY = ["--min-points", "3", "--max-points", "3", "--max-lanes", "1", "--aerial-stride", "3", "--aerial-yaws", "2"]


@pytest.fixture
def tiny_protocol(tmp_path, monkeypatch):
    """carla-town04's text with 16x12 images, as protocol carla-tiny@1 (fast renders)."""
    from skyeyes_bench.protocol import protocols_dir

    root = tmp_path / "protocols"
    (root / "carla-tiny").mkdir(parents=True)
    text = (protocols_dir() / "carla-town04" / "v1.toml").read_text()
    text = text.replace('id = "carla-town04"', 'id = "carla-tiny"').replace("width = 512", "width = 16")
    (root / "carla-tiny" / "v1.toml").write_text(text.replace("height = 512", "height = 12"))
    monkeypatch.setenv("SKYEYES_PROTOCOLS", str(root))
    return "carla-tiny"


def _run(tmp_path, monkeypatch, module, *extra, check=0):
    wfile = tmp_path / "w.json"
    wfile.write_text(json.dumps(waypoints_json()))
    monkeypatch.setitem(sys.modules, "carla", module)
    return run_cli("data", "capture-carla", "--town", "Town04", "--out", str(tmp_path / "cap"), "--protocol",
                   "carla-tiny", "--waypoints", str(wfile), "--no-progress", "--timeout", "0.2", *TINY, *extra,
                   check=check)


def test_capture_fake_server_retries_resumes_and_imports(tiny_protocol, tmp_path, monkeypatch, caplog):
    cap = tmp_path / "cap"
    # 1. 3 points x 8 yaws + 1 aerial point x 2 yaws = 26 frames; tick 1 settles the sensors.
    #    Tick 3 times out, tick 5 loses its depth image (both retried); the server dies after tick 9.
    first = fake_carla(map_name="Carla/Maps/Town01", fail_at={3}, drop_at={5}, stop_after=9)
    _, _, err = _run(tmp_path, monkeypatch, first, "--retries", "1", check=2)
    assert "no image from the CARLA server after 2 attempts (RuntimeError: time-out" in err
    assert "run the same command again to resume" in err and err.count("\n") == 1
    assert first.log["loaded"] == ["Town04"]  # another map was loaded: the town was loaded
    assert first.log["settings"] == [(True, 0.05), (False, None)]  # synchronous, then restored
    assert first.log["destroyed"] == 2 and not (cap / "capture.json").exists()
    assert "attempt 1: RuntimeError: time-out" in caplog.text and "attempt 1: sensor time-out" in caplog.text
    plan = json.loads((cap / "plan.json").read_text())
    done = [r for r in plan["frames"] if (cap / r["image"]).is_file()]
    assert len(done) == 9 - 1 - 2  # ticks 2..9 minus the two failed attempts
    # 2. Run again: only the missing frames are rendered.
    second = fake_carla()
    _, stdout, _ = _run(tmp_path, monkeypatch, second)
    assert f"wrote {cap / 'capture.json'}: 20 frames rendered, 6 kept from an earlier run" in stdout
    assert second.log["ticks"] == 1 + 20
    capture = json.loads((cap / "capture.json").read_text())
    assert capture["frames"] == plan["frames"] and capture["captured"]["server"] == "localhost:2000"
    # 3. Every file holds what the sensor saw from its planned transform (RGB from BGRA).
    for r in plan["frames"]:
        np.testing.assert_array_equal(imagefiles.read_image_uint8(cap / r["image"]),
                                      expected_pixels(r["location"], r["rotation"], 16, 12))
        np.testing.assert_array_equal(imagefiles.read_image_uint8(cap / r["depth"]),
                                      expected_pixels(r["location"], r["rotation"], 16, 12, depth=True))
    # 4. import-carla reads it; data check passes.
    run_cli("data", "import-carla", str(cap), str(tmp_path / "ds"), "--protocol", tiny_protocol, "--no-progress")
    ds = open_dataset(tmp_path / "ds", check_pixels=True)
    assert ds.protocol == "carla-tiny@1" and len(ds.scenes["Town04-lane00"].ground) == 24
    # 5. Nothing left to do: no server needed.
    _, stdout, _ = _run(tmp_path, monkeypatch, None)
    assert "0 frames rendered, 26 kept" in stdout


def test_capture_needs_the_carla_package(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "carla", None)  # import carla fails
    _, _, err = run_cli("data", "capture-carla", "--town", "Town04", "--out", str(tmp_path / "c"), check=2)
    assert err.startswith("skyeyes-bench: error: capture-carla needs the CARLA Python client")
    assert "pip install 'skyeyes-bench[carla]'" in err and err.count("\n") == 1


# A straight two-way road, 120 m along +x, one 3.5 m driving lane each side (OpenDRIVE 1.4).
XODR = """<?xml version="1.0" standalone="yes"?>
<OpenDRIVE>
  <header revMajor="1" revMinor="4" name="straight" version="1.00"/>
  <road name="r" length="120.0" id="7" junction="-1">
    <link/>
    <planView><geometry s="0.0" x="0.0" y="0.0" hdg="0.0" length="120.0"><line/></geometry></planView>
    <elevationProfile><elevation s="0" a="0" b="0" c="0" d="0"/></elevationProfile>
    <lateralProfile/>
    <lanes>
      <laneSection s="0.0">
        <left><lane id="1" type="driving" level="false"><link/><width sOffset="0" a="3.5" b="0" c="0" d="0"/></lane></left>
        <center><lane id="0" type="driving" level="false"><link/></lane></center>
        <right><lane id="-1" type="driving" level="false"><link/><width sOffset="0" a="3.5" b="0" c="0" d="0"/></lane></right>
      </laneSection>
    </lanes>
  </road>
</OpenDRIVE>
"""


def test_plan_from_opendrive_with_the_real_carla_package(tmp_path):
    pytest.importorskip("carla", reason="the carla package is not installed (pip install 'skyeyes-bench[carla]')")
    xodr = tmp_path / "Straight.xodr"
    xodr.write_text(XODR)
    cap = tmp_path / "cap"
    run_cli("data", "capture-carla", "--town", "Straight", "--out", str(cap), "--plan-only", "--xodr", str(xodr),
            "--waypoint-distance", "1.0")
    plan = json.loads((cap / "plan.json").read_text())
    (lane,) = plan["plan"]["lanes"]
    assert lane["road_id"] == 7 and abs(lane["lane_id"]) == 1 and lane["points"] == 32
    ground = [r for r in plan["frames"] if r["kind"] == "ground" and r["yaw_offset_deg"] == 0.0]
    xs = [r["location"][0] for r in sorted(ground, key=lambda r: r["index"])]
    steps = np.abs(np.diff(xs))
    np.testing.assert_allclose(steps, 2.0, atol=1e-3)  # every 2 m along the lane
    assert abs(abs(ground[0]["location"][1]) - 1.75) < 1e-3  # the lane centre, 1.75 m off the reference line
    assert all(r["location"][2] == pytest.approx(2.0, abs=1e-3) for r in ground)
    assert json.loads((cap / "waypoints.json").read_text())["town"] == "Straight"


def _server():
    host, _, port = os.environ.get("SKYEYES_CARLA", "localhost:2000").partition(":")
    try:
        socket.create_connection((host, int(port or 2000)), timeout=1.0).close()
    except OSError as e:
        return None, f"no CARLA server reachable at {host}:{port or 2000} ({e}); set SKYEYES_CARLA=host:port"
    return (host, port or "2000"), ""


def test_capture_on_a_real_server(tmp_path, tiny_protocol):
    pytest.importorskip("carla", reason="the carla package is not installed (pip install 'skyeyes-bench[carla]')")
    server, why = _server()
    if server is None:
        pytest.skip(why)
    cap = tmp_path / "cap"
    run_cli("data", "capture-carla", "--town", "Town04", "--out", str(cap), "--host", server[0], "--port", server[1],
            "--protocol", tiny_protocol, "--no-progress", *TINY)
    run_cli("data", "import-carla", str(cap), str(tmp_path / "ds"), "--protocol", tiny_protocol, "--no-progress")
    ds = open_dataset(tmp_path / "ds", check_pixels=True)
    assert len(ds.scenes) == 1 and all(np.isfinite(f.depth()).any() for f in ds.scenes["Town04-lane00"].ground)
