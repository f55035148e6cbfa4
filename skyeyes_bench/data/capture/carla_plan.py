"""The CARLA capture plan: which lanes of a town, and every camera transform, from the map's
waypoints alone (pure: no server, no files but the optional waypoint JSON).

How lanes are chosen (docs/formats.md, "CARLA capture"):

1. Waypoints of driving lanes outside junctions, as `carla.Map.generate_waypoints(d)` gives them
   (d <= the protocol's 2 m step), grouped by OpenDRIVE (road_id, section_id, lane_id).
2. A group is ordered along its direction of travel (by `s`, reversed when the waypoints' yaw points
   the other way) and cut into runs where two neighbours are more than 2.5 median spacings apart.
3. Each run is resampled every 2 m of horizontal arc length from its first waypoint (the lane's
   **start**); positions are interpolated linearly, the lane direction (yaw) along the arc. The lane
   **ends** after `max_points` points, or where the run ends. Runs with fewer than `min_points`
   points are dropped.
4. One lane per road (the longest run; ties: the smaller |lane_id|), so parallel lanes of one road
   do not make near-duplicate scenes. Lanes are ordered by (road_id, section_id, lane_id) and
   numbered 0..; with `max_lanes`, that many are taken evenly spaced in this order.

Cameras per lane point i (CARLA world, left-handed, degrees): ground cameras at the road surface +
2 m, pitch 0, yaw = lane yaw - k * 45 (a counter-clockwise offset of k * 45 deg in our right-handed
world, the convention of SynthTown and the MatrixCity importer); every `aerial_stride`-th point
`aerial_yaws` aerial cameras at the road surface + 52 m, pitch -45, yaws spread evenly.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ... import fields, inputfiles
from ...errors import UserError
from ..importers.carla import CARLA_FORMAT

_fail = fields.fail

WAYPOINTS_FORMAT = "skyeyes-carla-waypoints"
WAYPOINTS_FILE = "waypoints.json"
PLAN_FILE = "plan.json"


@dataclass(frozen=True)
class Waypoint:
    """One `carla.Waypoint`, as plain data (CARLA world: metres, left-handed; yaw in degrees)."""

    road_id: int
    section_id: int
    lane_id: int
    s: float  # metres along the road's reference line
    location: tuple[float, float, float]
    yaw: float  # direction of travel of the lane
    is_junction: bool = False
    lane_type: str = "Driving"


@dataclass(frozen=True)
class PlanConfig:
    """Capture geometry (from the protocol) and lane choice (options)."""

    step_m: float
    ground_height_m: float
    aerial_height_m: float
    aerial_pitch_deg: float
    yaws_deg: tuple[float, ...]
    width: int
    height: int
    fov_deg: float
    min_points: int = 16  # one 16-frame FVD clip per sequence
    max_points: int = 32
    max_lanes: int | None = None
    aerial_stride: int = 4
    aerial_yaws: int = 8

    @classmethod
    def from_protocol(cls, protocol, **options) -> "PlanConfig":
        c, d = protocol.capture, protocol.data
        cfg = cls(step_m=c.ground_step_m, ground_height_m=c.ground_height_m, aerial_height_m=c.aerial_height_m,
                  aerial_pitch_deg=c.aerial_pitch_deg, yaws_deg=tuple(c.yaws_deg), width=d.width, height=d.height,
                  fov_deg=d.fov_deg, **{k: v for k, v in options.items() if v is not None})
        for name in ("min_points", "max_points", "aerial_stride", "aerial_yaws"):
            if getattr(cfg, name) < 1:
                raise UserError(f"--{name.replace('_', '-')} {getattr(cfg, name)}: expected an integer >= 1")
        if cfg.min_points < 2 or cfg.max_points < cfg.min_points:
            raise UserError(f"--min-points {cfg.min_points} / --max-points {cfg.max_points}: expected "
                            "2 <= min <= max")
        if cfg.max_lanes is not None and cfg.max_lanes < 1:
            raise UserError(f"--max-lanes {cfg.max_lanes}: expected an integer >= 1")
        return cfg


@dataclass
class Lane:
    number: int
    road_id: int
    section_id: int
    lane_id: int
    start_s: float
    points: np.ndarray = field(repr=False)  # [N, 3] CARLA metres, road surface
    yaws: np.ndarray = field(repr=False)  # [N] CARLA degrees, direction of travel


# --------------------------------------------------------------------------- waypoint files


def waypoints_document(town: str, waypoints: list[Waypoint], distance_m: float) -> dict:
    """The JSON document `read_waypoints` reads (`capture-carla` writes it as waypoints.json)."""
    return {"format": WAYPOINTS_FORMAT, "version": 1, "town": town, "distance_m": distance_m,
            "waypoints": [{"road_id": w.road_id, "section_id": w.section_id, "lane_id": w.lane_id, "s": w.s,
                           "location": list(w.location), "yaw": w.yaw, "is_junction": w.is_junction,
                           "lane_type": w.lane_type} for w in waypoints]}


def read_waypoints(path: str | Path) -> tuple[str, list[Waypoint]]:
    """(town, waypoints) from a waypoint JSON file (docs/formats.md); one-line errors."""
    path = Path(path)
    raw = inputfiles.read_json(path)
    if not isinstance(raw, dict) or raw.get("format") != WAYPOINTS_FORMAT:
        _fail(f"{path}: field 'format'", f"expected {WAYPOINTS_FORMAT!r}")
    if raw.get("version") != 1:
        _fail(f"{path}: field 'version'", f"expected 1, got {raw.get('version')!r}")
    town = fields.name(f"{path}: field 'town'", raw.get("town"), "a town name such as 'Town04'")
    items = raw.get("waypoints")
    if not isinstance(items, list) or not items:
        _fail(f"{path}: field 'waypoints'", "expected a non-empty list")
    out = []
    for i, w in enumerate(items):
        at = f"{path}: waypoints[{i}]"
        if not isinstance(w, dict):
            _fail(at, "expected an object")
        ints = [fields.integer(f"{at}.{k}", w.get(k), "an OpenDRIVE id", -10**9, 10**9)
                for k in ("road_id", "section_id", "lane_id")]
        s = fields.number(f"{at}.s", w.get("s"), "metres along the road")
        loc = fields.numbers(f"{at}.location", w.get("location"), 3, "[x, y, z] in CARLA metres")
        yaw = fields.number(f"{at}.yaw", w.get("yaw"), "the lane's yaw in degrees")
        junction = w.get("is_junction", False)
        if not isinstance(junction, bool):
            _fail(f"{at}.is_junction", f"expected true or false, got {junction!r}")
        lane_type = w.get("lane_type", "Driving")
        if not isinstance(lane_type, str):
            _fail(f"{at}.lane_type", f"expected a CARLA lane type such as 'Driving', got {lane_type!r}")
        out.append(Waypoint(*ints, s, tuple(float(v) for v in loc), yaw, junction, lane_type))
    return town, out


# --------------------------------------------------------------------------- lanes


def _resample(points: np.ndarray, yaws: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points [N, 3] and yaws [N] (deg) of a run -> the same every `step` m of xy arc length."""
    seg = np.linalg.norm(np.diff(points[:, :2], axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    n = int(math.floor(arc[-1] / step + 1e-9)) + 1
    at = np.arange(n) * step
    pts = np.stack([np.interp(at, arc, points[:, j]) for j in range(3)], axis=1)
    rad = np.deg2rad(yaws)  # interpolate the direction, not the angle (wraps at +-180)
    c, s = np.interp(at, arc, np.cos(rad)), np.interp(at, arc, np.sin(rad))
    return pts, np.rad2deg(np.arctan2(s, c))


def _runs(group: list[Waypoint]) -> list[list[Waypoint]]:
    """A lane's waypoints ordered along its travel direction, cut where they jump."""
    group = sorted(group, key=lambda w: w.s)
    if len(group) >= 2:
        pts = np.array([w.location for w in group])
        steps = np.diff(pts[:, :2], axis=0)
        heading = np.array([[math.cos(math.radians(w.yaw)), math.sin(math.radians(w.yaw))] for w in group[:-1]])
        if float(np.sum(steps * heading)) < 0:  # waypoints' yaw points against increasing s
            group = group[::-1]
    if len(group) < 2:
        return [group]
    pts = np.array([w.location for w in group])
    gaps = np.linalg.norm(np.diff(pts[:, :2], axis=0), axis=1)
    limit = 2.5 * float(np.median(gaps))
    cuts = [0, *(i + 1 for i, g in enumerate(gaps) if g > limit or g < 1e-6), len(group)]
    return [group[a:b] for a, b in zip(cuts, cuts[1:]) if b > a]


def select_lanes(waypoints: list[Waypoint], cfg: PlanConfig) -> list[Lane]:
    """The lanes to capture (module docstring: steps 1-4)."""
    groups: dict[tuple[int, int, int], list[Waypoint]] = {}
    for w in waypoints:
        if w.lane_type == "Driving" and not w.is_junction:
            groups.setdefault((w.road_id, w.section_id, w.lane_id), []).append(w)
    best: dict[int, Lane] = {}
    for (road, section, lane_id), group in sorted(groups.items()):
        for run in _runs(group):
            if len(run) < 2:
                continue
            pts, yaws = _resample(np.array([w.location for w in run]), np.array([w.yaw for w in run]), cfg.step_m)
            if len(pts) < cfg.min_points:
                continue
            cand = Lane(-1, road, section, lane_id, run[0].s, pts[:cfg.max_points], yaws[:cfg.max_points])
            old = best.get(road)
            if old is None or (len(cand.points), -abs(lane_id)) > (len(old.points), -abs(old.lane_id)):
                best[road] = cand
    lanes = sorted(best.values(), key=lambda ln: (ln.road_id, ln.section_id, ln.lane_id))
    if cfg.max_lanes is not None and len(lanes) > cfg.max_lanes:
        keep = sorted(set(np.round(np.linspace(0, len(lanes) - 1, cfg.max_lanes)).astype(int)))
        lanes = [lanes[i] for i in keep]
    for i, ln in enumerate(lanes):
        ln.number = i
    return lanes


# --------------------------------------------------------------------------- plan


def _rec(kind: str, town: str, lane: int, image: str, depth: str, loc, pitch: float, yaw: float,
         cfg: PlanConfig, **extra) -> dict:
    yaw = (yaw + 180.0) % 360.0 - 180.0
    return {"kind": kind, "town": town, "lane": lane, **extra, "image": image, "depth": depth,
            "location": [round(float(v), 6) for v in loc], "rotation": [pitch, round(yaw, 6), 0.0],
            "fov": cfg.fov_deg, "width": cfg.width, "height": cfg.height}


def plan_capture(town: str, waypoints: list[Waypoint], cfg: PlanConfig) -> dict:
    """The capture plan: a document in `capture.json`'s format (docs/formats.md, read by
    `data import-carla`) with every frame's sensor transform and file names, plus `plan` (the
    configuration and the chosen lanes). Raises UserError when no lane qualifies."""
    fields.name("--town", town, "a town name such as 'Town04'")
    lanes = select_lanes(waypoints, cfg)
    if not lanes:
        raise UserError(f"{town}: no driving lane outside junctions has {cfg.min_points} points "
                        f"{cfg.step_m:g} m apart ({len(waypoints)} waypoints); lower --min-points?")
    frames = []
    for ln in lanes:
        folder = f"{town}/lane{ln.number:02d}"
        for i, (p, yaw) in enumerate(zip(ln.points, ln.yaws)):
            for off in cfg.yaws_deg:
                name = f"ground_yaw{int(round(off)) % 360:03d}_{i:04d}"
                frames.append(_rec("ground", town, ln.number, f"{folder}/rgb/{name}.png", f"{folder}/depth/{name}.png",
                                   p + [0, 0, cfg.ground_height_m], 0.0, yaw - off, cfg,
                                   yaw_offset_deg=off, index=i))
        for i in range(0, len(ln.points), cfg.aerial_stride):
            for k in range(cfg.aerial_yaws):
                off = k * 360.0 / cfg.aerial_yaws
                name = f"aerial_{i:04d}_{k:02d}"
                frames.append(_rec("aerial", town, ln.number, f"{folder}/rgb/{name}.png", f"{folder}/depth/{name}.png",
                                   ln.points[i] + [0, 0, cfg.aerial_height_m], cfg.aerial_pitch_deg,
                                   ln.yaws[i] - off, cfg))
    lane_info = [{"lane": ln.number, "road_id": ln.road_id, "section_id": ln.section_id, "lane_id": ln.lane_id,
                  "start_s": round(ln.start_s, 4), "points": len(ln.points),
                  "start": [round(float(v), 4) for v in ln.points[0]],
                  "end": [round(float(v), 4) for v in ln.points[-1]]} for ln in lanes]
    cfg_doc = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items()}
    return {"format": CARLA_FORMAT, "version": 1, "town": town,
            "plan": {"config": cfg_doc, "lanes": lane_info}, "frames": frames}
