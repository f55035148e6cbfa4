"""The CARLA capture plan (skyeyes_bench.data.capture.carla_plan) on a synthetic map whose
geometry is known in closed form (builders.carla_capture): which lanes, where they start, a point
every 2 m, and every camera checked in our world after `data import-carla` against the protocol
carla-town04@1 (2 m / pitch 0 / yaws k*45 CCW; 52 m / pitch -45; 512x512, fov 90)."""

import json
import math
import shutil

import numpy as np
import pytest
from builders.carla_capture import R1_START, R1_YAW, R2_CENTRE, R2_RADIUS, make_waypoints, road1_point, waypoints_json
from conftest import run_cli

from skyeyes_bench import imagefiles
from skyeyes_bench.data.capture import PlanConfig, plan_capture, read_waypoints, select_lanes
from skyeyes_bench.data.layout import open_dataset
from skyeyes_bench.protocol import load_protocol

PROTO = load_protocol("carla-town04@1")


def _cfg(**kw):
    return PlanConfig.from_protocol(PROTO, **{"min_points": 8, "max_points": 12, **kw})


def test_select_lanes_by_the_documented_rules():
    lanes = select_lanes(make_waypoints(), _cfg())
    # road 1: lane -1 (40 m, 12 points kept of 21) beats lane 1 (20 m) and its own 10 m run after
    # the gap; road 2: the arc, reversed to its direction of travel; road 3 (10 m = 6 points) too
    # short; road 4 (junction) and road 5 (sidewalk) never lanes.
    assert [(ln.number, ln.road_id, ln.lane_id, len(ln.points)) for ln in lanes] == [(0, 1, -1, 12), (1, 2, -1, 12)]
    r1, r2 = lanes
    assert r1.start_s == 100.0 and r2.start_s == 60.0  # road 2 starts where s is largest
    np.testing.assert_allclose(r1.points, [road1_point(2.0 * i) for i in range(12)], atol=1e-9)
    np.testing.assert_allclose(r1.yaws, R1_YAW, atol=1e-9)
    # road 2: consecutive points 2 m apart along the arc (chord 2 R sin(1 / R)), all on the circle
    chord = np.linalg.norm(np.diff(r2.points[:, :2], axis=0), axis=1)
    np.testing.assert_allclose(chord, 2 * R2_RADIUS * math.sin(1.0 / R2_RADIUS), rtol=1e-3)
    np.testing.assert_allclose(np.linalg.norm(r2.points[:, :2] - R2_CENTRE, axis=1), R2_RADIUS, rtol=1e-3)
    np.testing.assert_allclose(r2.points[0, :2], R2_CENTRE + [R2_RADIUS, 0.0], atol=1e-9)
    # max_lanes takes lanes evenly spaced in road order; max_points cuts from the start
    assert [ln.road_id for ln in select_lanes(make_waypoints(), _cfg(max_lanes=1))] == [1]
    assert len(select_lanes(make_waypoints(), _cfg(max_points=30))[0].points) == 21
    # coarser waypoints (2 m) give the same lane start and direction
    coarse = select_lanes(make_waypoints(spacing=2.0), _cfg())
    np.testing.assert_allclose(coarse[0].points, r1.points, atol=1e-9)


def test_plan_records():
    plan = plan_capture("Town04", make_waypoints(), _cfg(aerial_stride=4, aerial_yaws=4))
    assert plan["format"] == "skyeyes-carla-capture" and plan["version"] == 1
    ground = [r for r in plan["frames"] if r["kind"] == "ground"]
    aerial = [r for r in plan["frames"] if r["kind"] == "aerial"]
    assert len(ground) == 2 * 12 * 8 and len(aerial) == 2 * 3 * 4
    assert len({r["image"] for r in plan["frames"]}) == len(plan["frames"])
    r = next(r for r in ground if r["lane"] == 0 and r["index"] == 3 and r["yaw_offset_deg"] == 90.0)
    np.testing.assert_allclose(r["location"], road1_point(6.0) + [0, 0, 2.0], atol=1e-6)
    assert r["rotation"] == [0.0, R1_YAW - 90.0, 0.0] and (r["width"], r["height"], r["fov"]) == (512, 512, 90.0)
    assert plan["plan"]["lanes"][0]["start"] == pytest.approx(list(R1_START), abs=1e-4)


def _fill_images(root, plan, rgb_value=90):
    """Stand-in pixels at every planned path (what the server would render): a flat RGB and a
    depth-camera code of 10 m."""
    w, h = plan["frames"][0]["width"], plan["frames"][0]["height"]
    code = round(10.0 / 1000.0 * (2**24 - 1))
    depth = np.zeros((h, w, 3), np.uint8)
    depth[..., 0], depth[..., 1], depth[..., 2] = code & 255, (code >> 8) & 255, code >> 16
    rgb = np.full((h, w, 3), rgb_value, np.uint8)
    for r in plan["frames"]:
        imagefiles.write_image(root / r["image"], rgb)
        imagefiles.write_image(root / r["depth"], depth)


def _travel(points):
    """Unit direction of travel at each point of a lane [N, 2] (central differences)."""
    d = np.gradient(points, axis=0)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_plan_only_is_imported_and_checked_against_the_protocol(tmp_path):
    wfile = tmp_path / "waypoints.json"
    wfile.write_text(json.dumps(waypoints_json()))
    cap = tmp_path / "cap"
    _, stdout, _ = run_cli("data", "capture-carla", "--town", "Town04", "--out", str(cap), "--plan-only",
                           "--waypoints", str(wfile), "--min-points", "7", "--max-points", "7",
                           "--aerial-stride", "3", "--aerial-yaws", "4")
    assert stdout.strip() == (f"planned {cap / 'plan.json'}: 2 lanes, 112 ground and 24 aerial frames "
                              "(Town04, protocol carla-town04@1)")
    plan = json.loads((cap / "plan.json").read_text())
    assert not (cap / "capture.json").exists() and not (cap / "waypoints.json").exists()
    _fill_images(cap, plan)
    shutil.copy(cap / "plan.json", cap / "capture.json")  # what a finished capture writes, plus 'captured'
    out = tmp_path / "ds"
    run_cli("data", "import-carla", str(cap), str(out), "--no-progress")
    _, stdout, _ = run_cli("data", "check", str(out), "--quick")
    assert "protocol carla-town04@1" in stdout and stdout.strip().endswith("OK")
    ds = open_dataset(out)
    assert ds.splits == {"train": (), "test": ("Town04-lane00", "Town04-lane01")}
    cap_ = PROTO.capture
    flip = np.array([1.0, -1.0, 1.0])  # CARLA world -> ours
    for name, truth in (("Town04-lane00", np.array([road1_point(2.0 * i) for i in range(7)]) * flip),
                        ("Town04-lane01", None)):
        scene = ds.scenes[name]
        assert list(scene.sequences) == [f"yaw{int(y):03d}" for y in cap_.yaws_deg]
        centres = np.array([f.camera().center for f in scene.sequences["yaw000"]])  # [N, 3], our world
        if truth is not None:
            np.testing.assert_allclose(centres, truth + [0, 0, cap_.ground_height_m], atol=1e-5)
        steps = np.linalg.norm(np.diff(centres[:, :2], axis=0), axis=1)
        np.testing.assert_allclose(steps, cap_.ground_step_m, rtol=2e-4)  # chord of a 2 m arc on road 2
        travel = _travel(centres[:, :2])
        for seq, frames in scene.sequences.items():
            off = math.radians(int(seq[3:]))
            rot = np.array([[math.cos(off), -math.sin(off)], [math.sin(off), math.cos(off)]])  # CCW in our world
            for f, t in zip(frames, travel):
                cam = f.camera()
                np.testing.assert_allclose(cam.center, centres[f.index], atol=1e-5)
                np.testing.assert_allclose(cam.forward[:2], rot @ t, atol=2e-2)  # lane yaw vs chord direction
                assert cam.forward[2] == pytest.approx(math.sin(math.radians(cap_.ground_pitch_deg)), abs=1e-9)
                assert cam.c2w[:3, 0][2] == pytest.approx(0.0, abs=1e-9)  # no roll
                assert (cam.width, cam.height, cam.fov_x_deg) == (512, 512, pytest.approx(90.0))
        assert len(scene.aerial) == 3 * 4  # points 0, 3, 6
        road_z = centres[:, 2] - cap_.ground_height_m
        for a in scene.aerial:
            cam = a.camera()
            i = int(np.argmin(np.linalg.norm(centres[:, :2] - cam.center[:2], axis=1)))
            assert np.linalg.norm(centres[i, :2] - cam.center[:2]) < 1e-5 and i % 3 == 0  # over every 3rd point
            assert cam.center[2] - road_z[i] == pytest.approx(cap_.aerial_height_m, abs=1e-5)
            assert math.degrees(math.asin(cam.forward[2])) == pytest.approx(cap_.aerial_pitch_deg, abs=1e-6)
        np.testing.assert_allclose(scene.ground[0].depth(), 10.0, rtol=1e-6)


def test_plan_only_refusals(tmp_path):
    wfile = tmp_path / "w.json"
    wfile.write_text(json.dumps(waypoints_json()))
    cap = tmp_path / "cap"
    base = ["data", "capture-carla", "--town", "Town04", "--out", str(cap), "--plan-only", "--waypoints", str(wfile)]
    run_cli(*base, "--min-points", "4")
    run_cli(*base, "--min-points", "4")  # the same plan again: fine (a capture resumes this way)
    _, _, err = run_cli(*base, "--min-points", "7", check=2)  # another plan in the same folder
    assert f"{cap / 'plan.json'}: a capture of another plan" in err and err.count("\n") == 1
    run_cli(*base, "--min-points", "7", "--force")
    _, _, err = run_cli(*base[:3], "Town01", *base[4:], check=2)
    assert f"{wfile}: field 'town' is 'Town04', expected 'Town01' (--town)" in err
    _, _, err = run_cli(*base, "--min-points", "50", "--max-points", "60", check=2)
    assert "Town04: no driving lane outside junctions has 50 points 2 m apart" in err
    _, _, err = run_cli(*base, "--max-points", "1", check=2)
    assert "--min-points 16 / --max-points 1: expected 2 <= min <= max" in err
    raw = waypoints_json()
    raw["waypoints"][3]["location"] = [1, "y", 2]
    wfile.write_text(json.dumps(raw))
    _, _, err = run_cli(*base, check=2)
    assert f"{wfile}: waypoints[3].location: expected [x, y, z] in CARLA metres" in err and err.count("\n") == 1


def test_waypoints_round_trip(tmp_path):
    p = tmp_path / "w.json"
    p.write_text(json.dumps(waypoints_json(spacing=2.0)))
    town, wps = read_waypoints(p)
    assert town == "Town04" and wps == make_waypoints(spacing=2.0)
