"""Procedural town: a street grid with blocks, buildings, trees and parked cars.

Pure and deterministic: `make_town(name, seed, blocks)` returns the same `Town` for the same
arguments on any machine (numpy's PCG64 stream, no time or hash randomisation). Geometry is a
list of axis-aligned boxes, a list of ellipsoids (tree crowns) and the ground plane z = 0, whose
painted markings the renderer computes from the street grid stored here.

The stiff towns (`STIFF`) break two things a method may assume of a street: the whole town is
tilted in the world (a rigid rotation, `Town.world`: its streets climb and lean) and its sky is
cloudy (`Town.clouds`). Their geometry in town coordinates is made exactly as any town's.

Street cross-section (metres from a street's centre line): 0..3.5 driving lane, 3.5..6 parking
strip (road), then the block's raised sidewalk (kerb 0.15 m) 3.5 m wide, then the lots.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import numpy as np

# Box kinds (what a box is; the renderer picks a material and a semantic label from it).
SIDEWALK, GRASS, BUILDING, ROOFUNIT, CAR_BODY, CAR_CABIN, CAR_BASE, TRUNK = range(8)

ROAD_HALF_WIDTH = 6.0  # m, centre line to kerb
DRIVE_LANE = 3.5  # m, width of one driving lane
SIDEWALK_WIDTH = 3.5  # m
KERB_HEIGHT = 0.15  # m
GRASS_HEIGHT = 0.17  # m, lawns sit just above the sidewalk so their faces never coincide

#: The stiff towns, by name: the tilt of the whole town (degrees, about a horizontal axis at
#: `tilt_axis_deg` from the x axis) and the sky's cloud cover (0..1, `render.cloud_cover`). A
#: 5 degree tilt about an axis 30 degrees off the street grid makes every lane climb and lean at
#: once: 2.5 and 4.3 degrees (a 4-8 % grade, a steep city street). Every other town is level
#: under a clear sky.
STIFF = {"stiff-0": {"tilt_deg": 5.0, "tilt_axis_deg": 30.0, "clouds": 0.55}}

# Linear-light albedos. NOTE: picked by eye to resemble common facade paints and brick.
FACADE_COLOURS = np.array([
    [0.62, 0.55, 0.42], [0.58, 0.27, 0.17], [0.70, 0.68, 0.62], [0.45, 0.45, 0.47],
    [0.70, 0.60, 0.35], [0.40, 0.44, 0.52], [0.75, 0.72, 0.66], [0.50, 0.33, 0.25],
    [0.55, 0.58, 0.50], [0.66, 0.46, 0.36],
])
ROOF_COLOURS = np.array([
    [0.30, 0.30, 0.30],  # gravel
    [0.10, 0.10, 0.11],  # tar
    [0.45, 0.16, 0.08],  # terracotta tiles
    [0.14, 0.25, 0.08],  # green roof
    [0.50, 0.52, 0.55],  # metal
])
CAR_COLOURS = np.array([
    [0.60, 0.03, 0.02], [0.02, 0.08, 0.35], [0.75, 0.75, 0.75], [0.03, 0.03, 0.03],
    [0.35, 0.36, 0.38], [0.80, 0.55, 0.05], [0.05, 0.25, 0.10], [0.85, 0.85, 0.82],
])


@dataclass
class Town:
    """A town's geometry and parameters. Arrays are float64 unless stated.

    Attributes:
        name, seed: identity ("train-0", dataset seed).
        xs, ys: street centre-line coordinates; streets along y sit at x = xs[i], streets along x
            at y = ys[j]. Blocks lie between consecutive streets.
        box_lo, box_hi: [N, 3] box corners (axis-aligned).
        box_kind: [N] int, one of SIDEWALK..TRUNK.
        box_obj: [N] int, index into the buildings table for BUILDING/ROOFUNIT, the car for car
            parts, -1 otherwise.
        box_colour: [N, 3] linear albedo.
        bld: per-building parameters (dict of arrays, see `_building_params`).
        ell_centre, ell_radii: [M, 3] tree crowns; ell_colour: [M, 3].
        sun: [3] unit vector towards the sun, in the world.
        lanes: list of camera paths (dicts: start [x, y], heading deg, street, side).
        world: [3, 3] rotation from town to world coordinates (a stiff town's tilt); None: the
            town is level, its coordinates the world's.
        clouds: the sky's cloud cover, 0 (clear) .. 1.
    """

    name: str
    seed: int
    xs: np.ndarray
    ys: np.ndarray
    box_lo: np.ndarray
    box_hi: np.ndarray
    box_kind: np.ndarray
    box_obj: np.ndarray
    box_colour: np.ndarray
    bld: dict
    ell_centre: np.ndarray
    ell_radii: np.ndarray
    ell_colour: np.ndarray
    sun: np.ndarray
    params: dict = field(default_factory=dict)
    world: np.ndarray | None = None
    clouds: float = 0.0

    def to_world(self, p) -> np.ndarray:
        """Town coordinates [..., 3] -> world coordinates (the same for a level town)."""
        p = np.asarray(p, dtype=np.float64)
        return p if self.world is None else p @ self.world.T

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x0, y0, x1, y1): the street grid's outer kerbs, metres."""
        return (self.xs[0] - ROAD_HALF_WIDTH, self.ys[0] - ROAD_HALF_WIDTH,
                self.xs[-1] + ROAD_HALF_WIDTH, self.ys[-1] + ROAD_HALF_WIDTH)


def town_rng(name: str, seed: int) -> np.random.Generator:
    """Independent stream per (dataset seed, town name); crc32 is stable across runs (hash() is not)."""
    return np.random.default_rng([int(seed), zlib.crc32(name.encode())])


class _Boxes:
    def __init__(self):
        self.lo, self.hi, self.kind, self.obj, self.colour = [], [], [], [], []

    def add(self, lo, hi, kind, obj=-1, colour=(0.5, 0.5, 0.5)):
        self.lo.append(lo)
        self.hi.append(hi)
        self.kind.append(kind)
        self.obj.append(obj)
        self.colour.append(colour)


class _Scenery:
    """What `make_town` accumulates from one random stream: boxes, building parameters, tree
    crowns and the number of parked cars."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.boxes = _Boxes()
        self.bld: dict[str, list] = {k: [] for k in (
            "x0", "y0", "facade", "window", "floor_h", "win_dx", "win_w", "win_h", "shop", "band", "roof",
            "roof_colour", "door_dx")}
        self.ell_c, self.ell_r, self.ell_col = [], [], []
        self.n_cars = 0

    def tree(self, x, y, size=1.0):
        """A tree at (x, y): a trunk box and an ellipsoid crown."""
        rng, boxes = self.rng, self.boxes
        h_trunk = rng.uniform(2.2, 3.2) * size
        boxes.add((x - 0.15, y - 0.15, 0.0), (x + 0.15, y + 0.15, h_trunk + 0.8), TRUNK, -1, (0.16, 0.10, 0.06))
        rxy = rng.uniform(1.6, 2.4) * size
        self.ell_c.append((x, y, h_trunk + rng.uniform(1.2, 1.8) * size))
        self.ell_r.append((rxy, rxy * rng.uniform(0.9, 1.1), rng.uniform(1.7, 2.6) * size))
        g = rng.uniform(0.7, 1.3)
        self.ell_col.append((0.05 * g, 0.14 * g * rng.uniform(0.9, 1.2), 0.03 * g))

    def car(self, cx, cy, along_x):
        """A parked car centred at (cx, cy), its length along x or y: base, body and cabin boxes."""
        rng, boxes, n_cars = self.rng, self.boxes, self.n_cars
        length, width = rng.uniform(4.0, 4.8), rng.uniform(1.7, 1.9)
        hl, hw = (length / 2, width / 2) if along_x else (width / 2, length / 2)
        col = CAR_COLOURS[rng.integers(len(CAR_COLOURS))] * rng.uniform(0.85, 1.1)
        boxes.add((cx - hl + 0.35 * along_x, cy - hw + 0.35 * (not along_x), 0.0),
                  (cx + hl - 0.35 * along_x, cy + hw - 0.35 * (not along_x), 0.32), CAR_BASE, n_cars, (0.02, 0.02, 0.02))
        boxes.add((cx - hl, cy - hw, 0.32), (cx + hl, cy + hw, 0.95), CAR_BODY, n_cars, tuple(col))
        c0, c1 = rng.uniform(0.2, 0.3), rng.uniform(0.15, 0.25)  # cabin set back from both ends
        if along_x:
            lo, hi = (cx - hl + c0 * length, cy - hw + 0.12), (cx + hl - c1 * length, cy + hw - 0.12)
        else:
            lo, hi = (cx - hw + 0.12, cy - hl + c0 * length), (cx + hw - 0.12, cy + hl - c1 * length)
        boxes.add((*lo, 0.95), (*hi, rng.uniform(1.4, 1.55)), CAR_CABIN, n_cars, tuple(col))
        self.n_cars += 1


def make_town(name: str, seed: int, blocks: tuple[int, int] = (4, 4), *, scale: int = 1) -> Town:
    """Generate a town.

    Args:
        name: town name; with `seed` it fixes the random stream.
        seed: dataset seed.
        blocks: blocks along x and y.
        scale: multiply the block counts (benchmarks: a town of `scale**2` times the area).
    """
    rng = town_rng(name, seed)
    nbx, nby = blocks[0] * scale, blocks[1] * scale
    xs, ys = _street_grid(rng, nbx, nby)
    centre_size = max(xs[-1] - xs[0], ys[-1] - ys[0]) / 2
    sc = _Scenery(rng)
    for bi in range(nbx):
        for bj in range(nby):
            x0, x1 = xs[bi] + ROAD_HALF_WIDTH, xs[bi + 1] - ROAD_HALF_WIDTH
            y0, y1 = ys[bj] + ROAD_HALF_WIDTH, ys[bj + 1] - ROAD_HALF_WIDTH
            _block(sc, x0, x1, y0, y1, centre_size)
    _parked_cars(sc, xs, ys)
    # Sun: elevation 35..55 deg, azimuth away from the street axes so shadows fall obliquely.
    elev = np.deg2rad(rng.uniform(35, 55))
    azim = np.deg2rad(rng.uniform(20, 70) + 90 * rng.integers(4))
    sun = np.array([np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)])
    t = _assemble(name, seed, [nbx, nby], xs, ys, sc, elev, azim, sun)
    if name in STIFF:  # no draws from the town's stream: its geometry is any town's
        stiff = STIFF[name]
        t.world = tilt_rotation(stiff["tilt_deg"], stiff["tilt_axis_deg"])
        t.clouds = float(stiff["clouds"])
        t.params.update(stiff)
    return t


def tilt_rotation(tilt_deg: float, axis_deg: float) -> np.ndarray:
    """[3, 3] rotation by `tilt_deg` about the horizontal axis at `axis_deg` from x (Rodrigues)."""
    a = np.array([np.cos(np.deg2rad(axis_deg)), np.sin(np.deg2rad(axis_deg)), 0.0])
    th = np.deg2rad(tilt_deg)
    cross = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.cos(th) * np.eye(3) + np.sin(th) * cross + (1.0 - np.cos(th)) * np.outer(a, a)


def _street_grid(rng, nbx: int, nby: int) -> tuple[np.ndarray, np.ndarray]:
    """Street centre lines xs [nbx + 1], ys [nby + 1], centred on the origin."""
    # Block sizes (between kerbs) vary per street so that no two towns share a grid.
    widths_x = rng.integers(22, 34, size=nbx) * 2.0
    widths_y = rng.integers(22, 34, size=nby) * 2.0
    xs = np.concatenate([[0.0], np.cumsum(widths_x + 2 * ROAD_HALF_WIDTH)])
    ys = np.concatenate([[0.0], np.cumsum(widths_y + 2 * ROAD_HALF_WIDTH)])
    xs -= xs[-1] / 2
    ys -= ys[-1] / 2
    return xs, ys


def _block(sc: _Scenery, x0, x1, y0, y1, centre_size) -> None:
    """One block between kerbs x0..x1, y0..y1: sidewalk, lawn, rows of buildings (or empty lots), street trees."""
    rng, boxes = sc.rng, sc.boxes
    boxes.add((x0, y0, 0.0), (x1, y1, KERB_HEIGHT), SIDEWALK, -1, (0.36, 0.35, 0.33))
    lx0, lx1, ly0, ly1 = x0 + SIDEWALK_WIDTH, x1 - SIDEWALK_WIDTH, y0 + SIDEWALK_WIDTH, y1 - SIDEWALK_WIDTH
    # Lawn in the interior (courtyards, empty lots); buildings stand on top of it.
    boxes.add((lx0, ly0, 0.0), (lx1, ly1, GRASS_HEIGHT), GRASS, -1, (0.09, 0.17, 0.05))
    # Downtown is taller: height scale falls off with distance from the town centre.
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    tall = 1.0 - 0.6 * min(1.0, np.hypot(cx, cy) / centre_size)
    park = rng.random() < 0.1
    depth_max = min(lx1 - lx0, ly1 - ly0) / 2 - 1.0
    # South and north rows span the full lot width; west and east rows fill between them.
    rows = []
    d_s = rng.uniform(10, min(18, depth_max))
    d_n = rng.uniform(10, min(18, depth_max))
    rows.append(("s", lx0, lx1, ly0, ly0 + d_s))
    rows.append(("n", lx0, lx1, ly1 - d_n, ly1))
    d_w = rng.uniform(10, min(18, depth_max))
    d_e = rng.uniform(10, min(18, depth_max))
    rows.append(("w", ly0 + d_s, ly1 - d_n, lx0, lx0 + d_w))
    rows.append(("e", ly0 + d_s, ly1 - d_n, lx1 - d_e, lx1))
    for side, a0, a1, b0, b1 in rows:
        _row(sc, side, a0, a1, b0, b1, park, tall)
    _street_trees(sc, x0, x1, y0, y1)


def _row(sc: _Scenery, side: str, a0, a1, b0, b1, park: bool, tall: float) -> None:
    """One row of lots facing street side `side`: a0..a1 along the street, b0..b1 across it."""
    rng = sc.rng
    a = a0
    while a1 - a > 6.0:
        w = rng.uniform(9.0, 20.0)
        if a1 - (a + w) < 8.0:
            w = a1 - a
        lo_a, hi_a = a, a + w
        a += w
        if park or rng.random() < 0.08:  # an empty lot: trees on the lawn
            if hi_a - lo_a > 6:
                for _ in range(rng.integers(1, 3)):
                    ta, tb = rng.uniform(lo_a + 2.5, hi_a - 2.5), rng.uniform(b0 + 2.5, b1 - 2.5)
                    sc.tree(*((ta, tb) if side in "sn" else (tb, ta)), size=rng.uniform(0.9, 1.3))
            continue
        # Footprint: frontage along the street; depth varies per building.
        depth = (b1 - b0) * rng.uniform(0.7, 1.0)
        if side in "sn":
            fb0, fb1 = (b0, b0 + depth) if side == "s" else (b1 - depth, b1)
            lo, hi = (lo_a + 0.01, fb0), (hi_a - 0.01, fb1)
        else:
            fb0, fb1 = (b0, b0 + depth) if side == "w" else (b1 - depth, b1)
            lo, hi = (fb0, lo_a + 0.01), (fb1, hi_a - 0.01)
        _building(rng, sc.boxes, sc.bld, lo, hi, tall)


def _street_trees(sc: _Scenery, x0, x1, y0, y1) -> None:
    """Street trees along the block's kerbs, clear of the corners (crosswalks)."""
    rng = sc.rng
    for side in "snwe":
        if side in "sn":
            y = y0 + 1.3 if side == "s" else y1 - 1.3
            pos = np.arange(x0 + 7.0, x1 - 6.0, rng.uniform(9.0, 13.0))
            for p in pos:
                if rng.random() < 0.55:
                    sc.tree(p, y)
        else:
            x = x0 + 1.3 if side == "w" else x1 - 1.3
            pos = np.arange(y0 + 7.0, y1 - 6.0, rng.uniform(9.0, 13.0))
            for p in pos:
                if rng.random() < 0.55:
                    sc.tree(x, p)


def _parked_cars(sc: _Scenery, xs: np.ndarray, ys: np.ndarray) -> None:
    """Parked cars in the parking strips along each street segment (never in intersections)."""
    rng = sc.rng
    nbx, nby = len(xs) - 1, len(ys) - 1
    park_off = ROAD_HALF_WIDTH - 1.25
    for j, y in enumerate(ys):
        for i in range(nbx):
            a0, a1 = xs[i] + ROAD_HALF_WIDTH + 5.0, xs[i + 1] - ROAD_HALF_WIDTH - 5.0
            for sgn in (-1, 1):
                if (j == 0 and sgn < 0) or (j == nby and sgn > 0):
                    continue
                for p in np.arange(a0 + 3.0, a1 - 3.0, 6.5):
                    if rng.random() < 0.4:
                        sc.car(p + rng.uniform(-0.5, 0.5), y + sgn * park_off, True)
    for i, x in enumerate(xs):
        for j in range(nby):
            a0, a1 = ys[j] + ROAD_HALF_WIDTH + 5.0, ys[j + 1] - ROAD_HALF_WIDTH - 5.0
            for sgn in (-1, 1):
                if (i == 0 and sgn < 0) or (i == nbx and sgn > 0):
                    continue
                for p in np.arange(a0 + 3.0, a1 - 3.0, 6.5):
                    if rng.random() < 0.4:
                        sc.car(x + sgn * park_off, p + rng.uniform(-0.5, 0.5), False)


def _assemble(name: str, seed: int, blocks: list, xs, ys, sc: _Scenery, elev, azim, sun) -> Town:
    """The `Town` of the accumulated scenery, with its parameters (`Town.params`)."""
    boxes, ell_c = sc.boxes, sc.ell_c
    bld_arr = {k: np.asarray(v, dtype=np.float64) for k, v in sc.bld.items()}
    t = Town(
        name=name, seed=int(seed), xs=xs, ys=ys,
        box_lo=np.asarray(boxes.lo, dtype=np.float64), box_hi=np.asarray(boxes.hi, dtype=np.float64),
        box_kind=np.asarray(boxes.kind, dtype=np.int64), box_obj=np.asarray(boxes.obj, dtype=np.int64),
        box_colour=np.asarray(boxes.colour, dtype=np.float64), bld=bld_arr,
        ell_centre=np.asarray(ell_c, dtype=np.float64).reshape(-1, 3),
        ell_radii=np.asarray(sc.ell_r, dtype=np.float64).reshape(-1, 3),
        ell_colour=np.asarray(sc.ell_col, dtype=np.float64).reshape(-1, 3), sun=sun,
    )
    t.params = {
        "name": name, "seed": int(seed), "rng_stream": [int(seed), zlib.crc32(name.encode())], "blocks": blocks,
        "streets_x_m": [round(float(v), 3) for v in xs], "streets_y_m": [round(float(v), 3) for v in ys],
        "road_half_width_m": ROAD_HALF_WIDTH, "sidewalk_width_m": SIDEWALK_WIDTH, "kerb_height_m": KERB_HEIGHT,
        "sun_elevation_deg": round(float(np.rad2deg(elev)), 3), "sun_azimuth_deg": round(float(np.rad2deg(azim)), 3),
        "buildings": int(len(bld_arr["x0"])), "trees": len(ell_c), "cars": sc.n_cars, "boxes": len(boxes.lo),
        "max_height_m": round(float(t.box_hi[:, 2].max()), 3),
    }
    return t


def _building(rng, boxes: _Boxes, bld: dict, lo, hi, tall: float) -> None:
    """One building on footprint lo..hi (x, y): facade/roof parameters, boxes, rooftop units."""
    k = len(bld["x0"])
    floor_h = rng.uniform(3.0, 3.6)
    floors = int(np.clip(np.round(rng.gamma(3.0, 1.3) * (0.6 + 1.6 * tall)), 2, 14))
    h = floors * floor_h + rng.uniform(0.3, 0.8)  # parapet above the last floor
    colour = FACADE_COLOURS[rng.integers(len(FACADE_COLOURS))] * rng.uniform(0.85, 1.1, size=3)
    roof = int(rng.choice(5, p=[0.35, 0.2, 0.2, 0.1, 0.15]))
    bld["x0"].append(lo[0])
    bld["y0"].append(lo[1])
    bld["facade"].append(np.clip(colour, 0, 0.9))
    bld["window"].append(np.array([0.04, 0.06, 0.09]) * rng.uniform(0.7, 1.6))
    bld["floor_h"].append(floor_h)
    bld["win_dx"].append(rng.uniform(2.4, 3.6))
    bld["win_w"].append(rng.uniform(0.35, 0.65))
    bld["win_h"].append(rng.uniform(0.4, 0.65))
    bld["shop"].append(float(rng.random() < 0.45))
    bld["band"].append(float(rng.random() < 0.5))
    bld["roof"].append(roof)
    bld["roof_colour"].append(ROOF_COLOURS[roof] * rng.uniform(0.85, 1.15))
    bld["door_dx"].append(rng.uniform(0.3, 0.7))
    boxes.add((lo[0], lo[1], 0.0), (hi[0], hi[1], h), BUILDING, k, tuple(colour))
    w, d = hi[0] - lo[0], hi[1] - lo[1]
    if floors >= 5 and rng.random() < 0.35 and min(w, d) > 10:  # a set-back upper part
        inset = rng.uniform(2.0, 3.0)
        h2 = h + rng.integers(2, 6) * floor_h
        boxes.add((lo[0] + inset, lo[1] + inset, h - 0.01), (hi[0] - inset, hi[1] - inset, h2), BUILDING, k, tuple(colour))
        h = h2
        lo, hi = (lo[0] + inset, lo[1] + inset), (hi[0] - inset, hi[1] - inset)
    for _ in range(rng.integers(0, 4)):  # rooftop units (air handlers, stair houses)
        sx, sy, sz = rng.uniform(1.2, 3.5), rng.uniform(1.2, 3.5), rng.uniform(0.8, 2.5)
        if hi[0] - lo[0] < sx + 2 or hi[1] - lo[1] < sy + 2:
            continue
        ux, uy = rng.uniform(lo[0] + 1, hi[0] - 1 - sx), rng.uniform(lo[1] + 1, hi[1] - 1 - sy)
        boxes.add((ux, uy, h - 0.01), (ux + sx, uy + sy, h + sz), ROOFUNIT, k, (0.45, 0.45, 0.45))


def make_lanes(town: Town, n: int, frames: int, step_m: float, seed: int) -> list[dict]:
    """`n` distinct camera paths (lanes) of `frames` points `step_m` apart, in right-hand
    driving lanes, fully inside the street grid, not running over the grid's outer streets.

    Returns dicts with start [x, y] (metres), heading_deg, street ("x"|"y", index), length_m.
    """
    rng = np.random.default_rng([int(seed), zlib.crc32(town.name.encode()), 7])
    length = (frames - 1) * step_m
    cands = []
    for axis, coords, other in (("x", town.ys, town.xs), ("y", town.xs, town.ys)):
        for i in range(1, len(coords) - 1):  # inner streets: buildings on both sides
            for sgn in (1, -1):
                cands.append((axis, i, sgn))
    order = rng.permutation(len(cands))
    lanes = []
    for c in order:
        if len(lanes) == n:
            break
        axis, i, sgn = cands[c]
        coords, other = (town.ys, town.xs) if axis == "x" else (town.xs, town.ys)
        lo, hi = other[0] + 10.0, other[-1] - 10.0 - length
        if hi <= lo:
            continue
        s = float(np.round(rng.uniform(lo, hi) / step_m) * step_m)
        off = DRIVE_LANE / 2  # centre of the right-hand driving lane
        if axis == "x":
            heading = 0.0 if sgn > 0 else 180.0
            start = (s, coords[i] - off) if sgn > 0 else (s + length, coords[i] + off)
        else:
            heading = 90.0 if sgn > 0 else 270.0
            start = (coords[i] + off, s) if sgn > 0 else (coords[i] - off, s + length)
        lanes.append({"start": [float(start[0]), float(start[1])], "heading_deg": heading,
                      "street": [axis, i], "length_m": length})
    if len(lanes) < n:
        raise ValueError(f"town {town.name}: room for only {len(lanes)} lanes, {n} requested")
    return lanes


def from_boxes(box_lo, box_hi, *, kind: int = BUILDING, ellipsoids=None, sun=(0.3, 0.2, 0.9),
               name: str = "custom") -> Town:
    """A town made of the given boxes (all of one kind, plain facades) on open land, no streets.

    For tests and benchmarks: known geometry with the same renderer. box_lo/box_hi [N, 3];
    ellipsoids: optional (centres [M, 3], radii [M, 3]); sun: direction towards the sun.
    """
    lo = np.asarray(box_lo, dtype=np.float64).reshape(-1, 3)
    hi = np.asarray(box_hi, dtype=np.float64).reshape(-1, 3)
    n = len(lo)
    bld = {
        "x0": lo[:, 0].copy(), "y0": lo[:, 1].copy(), "facade": np.tile([0.6, 0.55, 0.45], (n, 1)),
        "window": np.tile([0.05, 0.06, 0.08], (n, 1)), "floor_h": np.full(n, 3.2), "win_dx": np.full(n, 3.0),
        "win_w": np.full(n, 0.5), "win_h": np.full(n, 0.5), "shop": np.zeros(n), "band": np.zeros(n),
        "roof": np.zeros(n), "roof_colour": np.tile(ROOF_COLOURS[0], (n, 1)), "door_dx": np.full(n, 0.5),
    }
    ec, er = (np.zeros((0, 3)), np.zeros((0, 3))) if ellipsoids is None else (
        np.asarray(ellipsoids[0], dtype=np.float64).reshape(-1, 3), np.asarray(ellipsoids[1], dtype=np.float64).reshape(-1, 3))
    s = np.asarray(sun, dtype=np.float64)
    far = np.array([-1e5, 1e5])  # streets far away: the ground is open land everywhere near
    return Town(name=name, seed=0, xs=far, ys=far, box_lo=lo, box_hi=hi, box_kind=np.full(n, kind, dtype=np.int64),
                box_obj=np.arange(n, dtype=np.int64) if kind in (BUILDING, ROOFUNIT) else np.full(n, -1, dtype=np.int64),
                box_colour=np.tile([0.5, 0.5, 0.5], (n, 1)), bld=bld, ell_centre=ec, ell_radii=er,
                ell_colour=np.tile([0.05, 0.15, 0.03], (len(ec), 1)), sun=s / np.linalg.norm(s))
