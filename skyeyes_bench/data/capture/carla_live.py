"""Render a capture plan on a CARLA server (`skyeyes-bench data capture-carla`).

One RGB and one depth camera (`sensor.camera.rgb`, `sensor.camera.depth`, the plan's size and
fov) are moved to each planned transform in synchronous mode: set the transform, `world.tick()`,
take the image of that tick from each sensor, check that the sensor stood where the plan says,
write both PNGs atomically. A sensor or server time-out is retried (`retries` times, then a
one-line error naming the frame); every finished frame stays on disk, so running the command
again resumes where it stopped. `capture.json` is written last, when every frame exists.

The `carla` package is imported lazily (`require_carla`): only this command needs it.
NOTE: API as documented for CARLA 0.9.x (Python API reference: carla.Client, World.tick,
WorldSettings.synchronous_mode, Sensor.listen, carla.Image.raw_data (BGRA), Image.transform).
"""

from __future__ import annotations

import logging
import queue
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ... import imagefiles, outputfiles
from ...errors import UserError
from ..importers.carla import CARLA_CAPTURE_FILE
from .carla_plan import Waypoint

log = logging.getLogger(__name__)


def require_carla():
    """The `carla` client module, or a one-line error saying how to get it."""
    try:
        import carla
    except ImportError as e:
        raise UserError(f"capture-carla needs the CARLA Python client ({e}): pip install 'skyeyes-bench[carla]', "
                        "or carla==<your server's version>") from None
    return carla


def waypoints_from_map(carla_map, distance_m: float) -> list[Waypoint]:
    """`carla.Map.generate_waypoints(distance_m)` (driving lanes) as plain `Waypoint`s."""
    out = []
    for w in carla_map.generate_waypoints(distance_m):
        t = w.transform
        out.append(Waypoint(int(w.road_id), int(w.section_id), int(w.lane_id), float(w.s),
                            (float(t.location.x), float(t.location.y), float(t.location.z)), float(t.rotation.yaw),
                            bool(w.is_junction), str(w.lane_type)))
    return out


def waypoints_from_xodr(path: Path, town: str, distance_m: float, carla=None) -> list[Waypoint]:
    """Waypoints of an OpenDRIVE file (CARLA ships `<town>.xodr`) without a server: `carla.Map`."""
    carla = carla or require_carla()
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise UserError(f"--xodr {path}: cannot read ({e})") from None
    try:
        cmap = carla.Map(town, text)
    except RuntimeError as e:
        raise UserError(f"--xodr {path}: not an OpenDRIVE map CARLA can read ({e})") from None
    return waypoints_from_map(cmap, distance_m)


@dataclass(frozen=True)
class Server:
    host: str = "localhost"
    port: int = 2000
    timeout_s: float = 20.0  # client calls and waiting for one sensor image
    retries: int = 3  # extra attempts per frame after a time-out
    fixed_delta_s: float = 0.05


def connect(server: Server, carla=None):
    """(carla module, client); a one-line error when the server does not answer."""
    carla = carla or require_carla()
    client = carla.Client(server.host, server.port)
    client.set_timeout(server.timeout_s)
    try:
        client.get_server_version()
    except RuntimeError as e:
        raise UserError(f"no CARLA server at {server.host}:{server.port} ({str(e).splitlines()[0]}); start "
                        "CarlaUE4 / CarlaUnreal, or pass --waypoints FILE / --xodr FILE with --plan-only") from None
    return carla, client


def town_world(client, town: str):
    """The server's world, loading `town` when another map is loaded."""
    world = client.get_world()
    if world.get_map().name.split("/")[-1] != town:
        log.info("loading %s", town)
        world = client.load_world(town)
    return world


def frame_done(out: Path, rec: dict) -> bool:
    """Both files of a planned frame exist with the planned size (an earlier run wrote them)."""
    try:
        return all(imagefiles.image_header(out / rec[k])[:2] == (rec["width"], rec["height"]) for k in ("image", "depth"))
    except (UserError, OSError):
        return False


def _pixels(image) -> np.ndarray:
    """carla.Image (BGRA bytes) -> uint8 [H, W, 3] RGB; for the depth camera the raw code."""
    px = np.frombuffer(image.raw_data, dtype=np.uint8).reshape(image.height, image.width, 4)
    return np.ascontiguousarray(px[..., [2, 1, 0]])


def _image_of(q: queue.Queue, frame: int, timeout: float):
    """The image of tick `frame` from a sensor's queue (older ones are dropped)."""
    while True:
        img = q.get(timeout=timeout)
        if img.frame == frame:
            return img
        if img.frame > frame:
            raise RuntimeError(f"sensor skipped frame {frame} (got {img.frame})")


def _stood_at(image, rec: dict) -> bool:
    """The sensor's transform in the image is the planned one (1 cm, 0.01 deg)."""
    t = image.transform
    loc = np.array([t.location.x, t.location.y, t.location.z])
    rot = np.array([t.rotation.pitch, t.rotation.yaw, t.rotation.roll])
    d = (rot - np.array(rec["rotation"]) + 180.0) % 360.0 - 180.0
    return bool(np.all(np.abs(loc - rec["location"]) < 0.01) and np.all(np.abs(d) < 0.01))


def capture(plan: dict, out: Path, server: Server, *, carla=None, progress: bool = True) -> tuple[int, int]:
    """Render every frame of `plan` not yet on disk under `out`; write `out/capture.json` when all
    exist. Returns (frames rendered now, frames found done)."""
    from tqdm import tqdm

    frames = plan["frames"]
    todo = [r for r in frames if not frame_done(out, r)]
    sizes = {(r["width"], r["height"], r["fov"]) for r in frames}
    if len(sizes) != 1:
        raise UserError(f"plan: frames of several sizes / fovs {sorted(sizes)}; expected one")
    width, height, fov = sizes.pop()
    if todo:
        carla, client = connect(server, carla)
        world = town_world(client, plan["town"])
        _render(carla, world, todo, out, server, width, height, fov, progress, tqdm)
    missing = [r["image"] for r in frames if not frame_done(out, r)]
    if missing:  # pragma: no cover - _render raises first
        raise UserError(f"{out}: {len(missing)} planned frames missing, e.g. {missing[0]}")
    doc = {**plan, "captured": {"server": f"{server.host}:{server.port}",
                                "fixed_delta_seconds": server.fixed_delta_s}}
    outputfiles.write_json(out / CARLA_CAPTURE_FILE, doc)
    return len(todo), len(frames) - len(todo)


def _render(carla, world, todo: list[dict], out: Path, server: Server, width: int, height: int, fov: float,
            progress: bool, tqdm) -> None:
    original = world.get_settings()
    settings = world.get_settings()
    settings.synchronous_mode = True
    settings.fixed_delta_seconds = server.fixed_delta_s
    world.apply_settings(settings)
    sensors: list[Any] = []
    try:
        lib = world.get_blueprint_library()
        queues = []
        for kind in ("sensor.camera.rgb", "sensor.camera.depth"):
            bp = lib.find(kind)
            bp.set_attribute("image_size_x", str(width))
            bp.set_attribute("image_size_y", str(height))
            bp.set_attribute("fov", str(fov))
            sensor = world.spawn_actor(bp, carla.Transform())
            sensors.append(sensor)
            q: queue.Queue = queue.Queue()
            sensor.listen(q.put)
            queues.append(q)
        world.tick()  # let the sensors settle before the first planned frame
        for rec in tqdm(todo, desc="capture", unit="frame", file=sys.stderr, disable=None if progress else True):
            _shoot(carla, world, sensors, queues, rec, out, server)
    finally:
        for s in sensors:
            try:
                s.stop()
                s.destroy()
            except RuntimeError:  # pragma: no cover - the server went away
                pass
        world.apply_settings(original)


def _shoot(carla, world, sensors, queues, rec: dict, out: Path, server: Server) -> None:
    """One planned frame: move both sensors, tick, take both images; retry on time-outs."""
    (x, y, z), (pitch, yaw, roll) = rec["location"], rec["rotation"]
    transform = carla.Transform(carla.Location(x=x, y=y, z=z), carla.Rotation(pitch=pitch, yaw=yaw, roll=roll))
    last = "no attempt"
    for attempt in range(server.retries + 1):
        for s in sensors:
            s.set_transform(transform)
        try:
            frame = world.tick(server.timeout_s)
            rgb, depth = (_image_of(q, frame, server.timeout_s) for q in queues)
        except (queue.Empty, RuntimeError) as e:  # a sensor or the server timed out
            last = f"{type(e).__name__}: {e}" if str(e) else "sensor time-out"
            log.warning("%s: attempt %d: %s", rec["image"], attempt + 1, last)
            continue
        if not (_stood_at(rgb, rec) and _stood_at(depth, rec)):
            last = "the sensor was not at the planned transform"
            log.warning("%s: attempt %d: %s", rec["image"], attempt + 1, last)
            continue
        imagefiles.write_image(out / rec["depth"], _pixels(depth))  # depth first: the RGB file marks done
        imagefiles.write_image(out / rec["image"], _pixels(rgb))
        return
    raise UserError(f"{rec['image']}: no image from the CARLA server after {server.retries + 1} attempts ({last}); "
                    "run the same command again to resume")
