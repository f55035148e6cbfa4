"""Synthetic CARLA map waypoints with their known geometry, and a fake `carla` client module (the
small part of the CARLA 0.9 Python API that capture-carla uses) that renders images as a known
function of the sensor's transform. No tests here."""

import math
import queue as _queue
import types

import numpy as np

from skyeyes_bench.data.capture import Waypoint, waypoints_document

#: Road 1: straight, CARLA yaw 30 deg, from (10, 5) rising 5 cm per metre; lane -1 (40 m) and
#: lane 1 (20 m, opposite direction: the longer lane -1 is kept).
R1_START, R1_YAW, R1_SLOPE = np.array([10.0, 5.0, 0.5]), 30.0, 0.05
#: Road 2: an arc of radius 50 around (200, 0), driven clockwise in CARLA's frame while the
#: waypoints' s runs the other way (the plan must reverse them); 60 m long.
R2_CENTRE, R2_RADIUS = np.array([200.0, 0.0]), 50.0


def road1_point(d):
    """Road surface point of road 1, lane -1, `d` m from its start (CARLA frame)."""
    y = math.radians(R1_YAW)
    return R1_START + d * np.array([math.cos(y), math.sin(y), R1_SLOPE])


def road2_point(d):
    """Road 2 (lane -1) `d` m of arc from its start, and its CARLA yaw there."""
    a = -d / R2_RADIUS  # angle decreasing: clockwise in CARLA's x-y axes
    p = np.array([R2_CENTRE[0] + R2_RADIUS * math.cos(a), R2_CENTRE[1] + R2_RADIUS * math.sin(a), 1.0])
    return p, math.degrees(a - math.pi / 2)


def make_waypoints(spacing=1.0):
    """The synthetic map: roads 1 and 2 as above; road 3 too short (10 m); road 4 only in a
    junction; road 5 a sidewalk; road 1 also has a second run after a gap (60..70 m, shorter)."""
    wps = []
    for i in range(int(40 / spacing) + 1):
        d = i * spacing
        p = road1_point(d)
        # road 1's horizontal arc length is d (the slope only changes z)
        wps.append(Waypoint(1, 0, -1, 100.0 + d, tuple(p), R1_YAW))
    for i in range(int(10 / spacing) + 1):  # the run after a gap: shorter, never chosen
        d = 60 + i * spacing
        wps.append(Waypoint(1, 0, -1, 100.0 + d, tuple(road1_point(d)), R1_YAW))
    for i in range(int(20 / spacing) + 1):
        d = i * spacing
        p = road1_point(20 - d) + [0.0, 3.5, 0.0]
        wps.append(Waypoint(1, 0, 1, 120.0 - d, tuple(p), R1_YAW + 180.0))
    for i in range(int(60 / spacing) + 1):
        d = i * spacing
        p, yaw = road2_point(d)
        wps.append(Waypoint(2, 1, -1, 60.0 - d, tuple(p), yaw))  # s decreases along travel
    for i in range(11):
        wps.append(Waypoint(3, 0, -1, float(i), (500.0 + i, 0.0, 0.0), 0.0))
    for i in range(41):
        wps.append(Waypoint(4, 0, -1, float(i), (0.0, 500.0 + i, 0.0), 90.0, is_junction=True))
        wps.append(Waypoint(5, 0, -2, float(i), (-500.0 - i, 0.0, 0.0), 180.0, lane_type="Sidewalk"))
    return wps


def waypoints_json(town="Town04", spacing=1.0):
    return waypoints_document(town, make_waypoints(spacing), spacing)


# --------------------------------------------------------------------------- fake carla


def expected_pixels(location, rotation, w, h, depth=False):
    """What the fake camera sees from a transform: RGB uint8 [H, W, 3] (a known function of it)."""
    seed = int(abs(hash((tuple(np.round(location, 3)), tuple(np.round(rotation, 3)), depth))) % (2**32))
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def fake_carla(*, map_name="Carla/Maps/Town04", fail_at=(), drop_at=(), stop_after=None):
    """A module with carla's names. `fail_at`: tick numbers whose world.tick raises a time-out;
    `drop_at`: ticks whose depth image never arrives; `stop_after`: every tick after this many
    raises (a server gone for good). `mod.log` records what happened."""
    mod = types.ModuleType("carla")
    mod.log = {"ticks": 0, "loaded": [], "settings": [], "destroyed": 0}

    class Location:
        def __init__(self, x=0.0, y=0.0, z=0.0):
            self.x, self.y, self.z = x, y, z

    class Rotation:
        def __init__(self, pitch=0.0, yaw=0.0, roll=0.0):
            self.pitch, self.yaw, self.roll = pitch, yaw, roll

    class Transform:
        def __init__(self, location=None, rotation=None):
            self.location, self.rotation = location or Location(), rotation or Rotation()

    class Image:
        def __init__(self, frame, transform, w, h, depth):
            self.frame, self.transform, self.width, self.height = frame, transform, w, h
            t = transform
            rgb = expected_pixels([t.location.x, t.location.y, t.location.z],
                                  [t.rotation.pitch, t.rotation.yaw, t.rotation.roll], w, h, depth)
            bgra = np.concatenate([rgb[..., ::-1], np.full((h, w, 1), 255, np.uint8)], axis=2)
            self.raw_data = bgra.tobytes()

    class Blueprint:
        def __init__(self, kind):
            self.kind, self.attrs = kind, {}

        def set_attribute(self, k, v):
            self.attrs[k] = v

    class Sensor:
        def __init__(self, bp, transform):
            self.bp, self.transform, self.callback = bp, transform, None

        def listen(self, cb):
            self.callback = cb

        def set_transform(self, t):
            self.transform = t

        def stop(self):
            self.callback = None

        def destroy(self):
            mod.log["destroyed"] += 1

    class Settings:
        def __init__(self, sync=False, delta=None):
            self.synchronous_mode, self.fixed_delta_seconds = sync, delta

    class World:
        def __init__(self, name):
            self.name, self.sensors, self.settings = name, [], Settings()

        def get_map(self):
            return types.SimpleNamespace(name=self.name)

        def get_settings(self):
            return Settings(self.settings.synchronous_mode, self.settings.fixed_delta_seconds)

        def apply_settings(self, s):
            self.settings = s
            mod.log["settings"].append((s.synchronous_mode, s.fixed_delta_seconds))

        def get_blueprint_library(self):
            return types.SimpleNamespace(find=Blueprint)

        def spawn_actor(self, bp, transform):
            s = Sensor(bp, transform)
            self.sensors.append(s)
            return s

        def tick(self, seconds=0.0):
            assert self.settings.synchronous_mode, "tick outside synchronous mode"
            mod.log["ticks"] += 1
            n = mod.log["ticks"]
            if n in fail_at or (stop_after is not None and n > stop_after):
                raise RuntimeError("time-out of 20000ms while waiting for the simulator")
            for s in self.sensors:
                depth = s.bp.kind.endswith("depth")
                if s.callback and not (depth and n in drop_at):
                    s.callback(Image(n, s.transform, int(s.bp.attrs["image_size_x"]),
                                     int(s.bp.attrs["image_size_y"]), depth))
            return n

    class Client:
        def __init__(self, host, port):
            self.world = World(map_name)

        def set_timeout(self, s):
            pass

        def get_server_version(self):
            return "0.9.16"

        def get_world(self):
            return self.world

        def load_world(self, town):
            mod.log["loaded"].append(town)
            self.world = World(f"Carla/Maps/{town}")
            return self.world

    mod.Location, mod.Rotation, mod.Transform, mod.Client = Location, Rotation, Transform, Client
    mod.queue = _queue
    return mod
