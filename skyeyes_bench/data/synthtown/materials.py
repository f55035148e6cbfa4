"""What a town's surfaces are made of: the semantic labels, value noise, and the albedo and label
of every hit (the ground plane's asphalt, paint and open land; facades, roofs, sidewalks, lawns,
cars, trunks). `render.surface` calls these; like it, they are float64 numpy with elementwise
arithmetic only.

Semantic labels (uint8, `PALETTE` gives display colours):

| id | class      | id | class                         |
|----|------------|----|-------------------------------|
| 0  | sky        | 5  | roof (top faces of buildings) |
| 1  | road       | 6  | vegetation (tree crowns)      |
| 2  | road line  | 7  | trunk                         |
| 3  | sidewalk   | 8  | car                           |
| 4  | building (facades, windows, doors) | 9 | terrain (lawns, open land) |
"""

from __future__ import annotations

import numpy as np

from . import town as tw

LABELS = ("sky", "road", "road line", "sidewalk", "building", "roof", "vegetation", "trunk", "car", "terrain")
SKY, ROAD, LINE, SIDEWALK, BUILDING, ROOF, VEGETATION, TRUNK, CAR, TERRAIN = range(10)
#: Display colours of the labels (NOTE: Cityscapes/CARLA-like colours where a class exists there).
PALETTE = np.array([
    [70, 130, 180], [128, 64, 128], [157, 234, 50], [244, 35, 232], [70, 70, 70],
    [190, 100, 60], [107, 142, 35], [153, 153, 153], [0, 0, 142], [152, 251, 152],
], dtype=np.uint8)


def colourise_labels(labels: np.ndarray) -> np.ndarray:
    """uint8 [H, W] labels -> uint8 [H, W, 3] palette colours."""
    return PALETTE[np.minimum(labels, len(PALETTE) - 1)]


# --------------------------------------------------------------------------- noise


def _hash(ix: np.ndarray, iy: np.ndarray, salt: int) -> np.ndarray:
    """Integer lattice hash -> [0, 1). Deterministic, platform independent (uint64 wraparound).

    NOTE: the odd multipliers and the xor-shift finaliser are SplitMix64's (Steele et al. 2014).
    """
    h = (ix.astype(np.int64).astype(np.uint64) * np.uint64(0x9E3779B185EBCA87)) ^ (
        iy.astype(np.int64).astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)) ^ np.uint64(salt * 0x165667B19E3779F9 & 0xFFFFFFFFFFFFFFFF)
    h ^= h >> np.uint64(29)
    h *= np.uint64(0xBF58476D1CE4E5B9)
    h ^= h >> np.uint64(32)
    return (h >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def vnoise(x: np.ndarray, y: np.ndarray, scale: float, salt: int = 0) -> np.ndarray:
    """Smooth value noise in [0, 1) with feature size `scale` metres."""
    x, y = x / scale, y / scale
    fx, fy = np.floor(x), np.floor(y)
    u, v = x - fx, y - fy
    u, v = u * u * (3 - 2 * u), v * v * (3 - 2 * v)
    a, b = _hash(fx, fy, salt), _hash(fx + 1, fy, salt)
    c, d = _hash(fx, fy + 1, salt), _hash(fx + 1, fy + 1, salt)
    return (a * (1 - u) + b * u) * (1 - v) + (c * (1 - u) + d * u) * v


# --------------------------------------------------------------------------- materials


def _nearest(coords: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index of and signed offset to the nearest value of sorted `coords` for each v."""
    j = np.clip(np.searchsorted(coords, v), 1, len(coords) - 1)
    left = np.abs(v - coords[j - 1]) <= np.abs(v - coords[j])
    j = np.where(left, j - 1, j)
    return j, v - coords[j]


def ground_material(town: tw.Town, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Albedo [P, 3] and label [P] of the ground plane at (x, y): asphalt, paint, or open land."""
    rh = tw.ROAD_HALF_WIDTH
    x0, y0, x1, y1 = town.extent
    inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    _, vy = _nearest(town.ys, y)  # across a street running along x
    _, vx = _nearest(town.xs, x)
    in_xs = inside & (np.abs(vy) < rh)
    in_ys = inside & (np.abs(vx) < rh)
    road = in_xs | in_ys
    inter = in_xs & in_ys
    n = vnoise(x, y, 0.7, 1) * 0.6 + vnoise(x, y, 5.0, 2) * 0.4
    asphalt = (0.055 + 0.035 * n)[:, None] * np.array([1.0, 1.0, 1.04])
    grass = np.array([0.07, 0.14, 0.04]) * (0.7 + 0.6 * vnoise(x, y, 2.0, 3))[:, None]
    albedo = np.where(road[:, None], asphalt, grass)
    label = np.where(road, ROAD, TERRAIN).astype(np.uint8)
    paint = np.zeros(len(x), dtype=bool)
    yellow = np.zeros(len(x), dtype=bool)
    for along, across, on in ((x, vy, in_xs & ~inter), (y, vx, in_ys & ~inter)):
        a = np.abs(across)
        # Distance along the street to the nearest crossing street's kerb line.
        cross = town.xs if along is x else town.ys
        _, dv = _nearest(cross, along)
        du = np.abs(dv) - rh
        centre = (a < 0.12) & (du > 5.0)
        yellow |= on & centre
        edge = (np.abs(a - tw.DRIVE_LANE) < 0.07) & (du > 5.0)
        zebra = (du > 0.8) & (du < 4.2) & (a < rh - 0.4) & (np.mod(across + 0.3, 1.2) < 0.6)
        # Stop lines on the approach side only: right-hand traffic on a street along x drives at
        # across < 0 heading +x (dv < 0 before the crossing); along y at across > 0 heading +y.
        approach = np.sign(dv) * np.sign(across) * (1 if along is x else -1) > 0
        stop = (du > 4.6) & (du < 5.0) & (a < tw.DRIVE_LANE) & approach
        paint |= on & (edge | zebra | stop)
    wear = (0.75 + 0.25 * vnoise(x, y, 0.5, 4))[:, None]
    albedo = np.where(paint[:, None], np.array([0.75, 0.75, 0.72]) * wear, albedo)
    albedo = np.where(yellow[:, None], np.array([0.75, 0.52, 0.08]) * wear, albedo)
    label = np.where(paint | yellow, LINE, label).astype(np.uint8)
    return albedo, label


def _facade(town: tw.Town, b: np.ndarray, p: np.ndarray, axis: np.ndarray, top: np.ndarray) -> np.ndarray:
    """Facade albedo [P, 3] for building ids b [P], points p [P, 3], face normal axis [P] (0 x, 1 y),
    box top z [P]: window grid per floor, frames, ledges, ground-floor shops or doors."""
    B = town.bld
    u = np.where(axis == 0, p[:, 1] - B["y0"][b], p[:, 0] - B["x0"][b])  # along the facade, m
    z = p[:, 2]
    fh, wdx = B["floor_h"][b], B["win_dx"][b]
    floor = np.floor(z / fh)
    fz = z / fh - floor  # 0..1 within the floor
    col = np.floor(u / wdx)
    cu = u / wdx - col  # 0..1 within the window column
    base = B["facade"][b] * (0.94 + 0.12 * vnoise(u + 31 * b, z, 1.5, 5))[:, None]
    ww, wh = B["win_w"][b] / 2, B["win_h"][b] / 2
    du, dz = np.abs(cu - 0.5), np.abs(fz - 0.55)
    frame_u, frame_z = 0.08 / wdx, 0.08 / fh
    upper = (floor >= 1) & (z < top - 0.9)
    win = upper & (du < ww) & (dz < wh)
    frame = upper & ~win & (du < ww + frame_u) & (dz < wh + frame_z)
    # Per-window glass variation (curtains, reflections), fixed per window.
    g = _hash(col + 1000 * b, floor, 6)
    glass = B["window"][b] * (0.6 + 1.4 * g)[:, None] + np.array([0.02, 0.025, 0.03]) * (fz > 0.55 + wh * 0.3)[:, None]
    out = np.where(win[:, None], glass, base)
    out = np.where(frame[:, None], np.array([0.55, 0.55, 0.52]), out)
    band = (B["band"][b] > 0) & (fz < 0.07) & (floor >= 1) & (z < top - 0.3)
    out = np.where(band[:, None], base * 0.62, out)
    # Ground floor: shop windows with mullions, or doors; a darker plinth.
    gf = floor == 0
    shop = gf & (B["shop"][b] > 0) & (z > 0.55) & (z < 2.7) & (du < 0.44)
    door = gf & (B["shop"][b] == 0) & (np.mod(col, 3) == 1) & (np.abs(cu - B["door_dx"][b]) < 0.42 / wdx * 1.2) & (z < 2.25)
    out = np.where(shop[:, None], glass * 1.3 + 0.02, out)
    out = np.where(door[:, None], np.array([0.16, 0.09, 0.05]) * (0.8 + 0.4 * _hash(col, b, 7))[:, None], out)
    plinth = gf & (z < 0.5) & ~door
    out = np.where(plinth[:, None], base * 0.55, out)
    # Contact darkening near the street (a cheap stand-in for ambient occlusion).
    return out * (0.72 + 0.28 * np.minimum(1.0, z / 2.5))[:, None]


def _roof(town: tw.Town, b: np.ndarray, p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Roof albedo [P, 3]: material per building (gravel, tar, tiles, green, metal), coping rim."""
    B = town.bld
    kind = B["roof"][b].astype(np.int64)
    base = B["roof_colour"][b]
    x, y = p[:, 0], p[:, 1]
    n1 = vnoise(x, y, 0.4, 8)
    n2 = vnoise(x, y, 3.0, 9)
    f = 0.8 + 0.25 * n1 + 0.15 * n2
    f = np.where(kind == 2, 0.75 + 0.35 * (np.mod(x * 2.5, 1.0) > 0.15) * (0.8 + 0.4 * n2), f)  # tile rows
    f = np.where(kind == 4, 0.85 + 0.25 * (np.mod(y * 1.25, 1.0) > 0.08), f)  # standing seams
    f = np.where(kind == 3, 0.6 + 0.8 * vnoise(x, y, 1.2, 10), f)
    out = base * f[:, None]
    rim = np.minimum(np.minimum(x - lo[:, 0], hi[:, 0] - x), np.minimum(y - lo[:, 1], hi[:, 1] - y)) < 0.35
    return np.where(rim[:, None], B["facade"][b] * 0.8, out)


def box_material(town: tw.Town, k, pb, lo, hi, axis, top):
    """Albedo [P, 3] and label [P] of hits pb on boxes `k` (corners lo, hi; hit face `axis`, `top` faces)."""
    kind = town.box_kind[k]
    col = town.box_colour[k].copy()
    lab = np.full(len(k), BUILDING, dtype=np.uint8)
    # Sidewalks: paving slabs with joints on top, a lighter kerb stone along the edge.
    sw = kind == tw.SIDEWALK
    if sw.any():
        x, y = pb[:, 0], pb[:, 1]
        joint = (np.mod(x / 1.5, 1.0) < 0.03) | (np.mod(y / 1.5, 1.0) < 0.03)
        edge = np.minimum(np.minimum(x - lo[:, 0], hi[:, 0] - x), np.minimum(y - lo[:, 1], hi[:, 1] - y)) < 0.25
        pav = col * (0.9 + 0.2 * vnoise(x, y, 1.5, 11))[:, None] * np.where(joint, 0.7, 1.0)[:, None]
        pav = np.where((edge | ~top)[:, None], np.array([0.5, 0.5, 0.48]), pav)
        col = np.where(sw[:, None], pav, col)
        lab[sw] = SIDEWALK
    gr = kind == tw.GRASS
    if gr.any():
        col = np.where(gr[:, None], col * (0.7 + 0.6 * vnoise(pb[:, 0], pb[:, 1], 1.7, 12))[:, None], col)
        lab[gr] = TERRAIN
    bl = (kind == tw.BUILDING) | (kind == tw.ROOFUNIT)
    if bl.any():
        bi = np.nonzero(bl)[0]
        b = town.box_obj[k[bi]]
        fac = (~top[bi]) & (axis[bi] < 2) & (kind[bi] == tw.BUILDING)
        out = col[bi]
        if fac.any():
            out[fac] = _facade(town, b[fac], pb[bi][fac], axis[bi][fac], hi[bi][fac][:, 2])
        rf = top[bi] & (kind[bi] == tw.BUILDING)
        if rf.any():
            out[rf] = _roof(town, b[rf], pb[bi][rf], lo[bi][rf], hi[bi][rf])
        unit = kind[bi] == tw.ROOFUNIT
        out[unit] = out[unit] * (0.85 + 0.3 * vnoise(pb[bi][unit][:, 0] + pb[bi][unit][:, 2], pb[bi][unit][:, 1], 0.6, 13))[:, None]
        col[bi] = out
        lab[bi] = np.where(top[bi] | (kind[bi] == tw.ROOFUNIT), ROOF, BUILDING)
    car = (kind == tw.CAR_BODY) | (kind == tw.CAR_CABIN) | (kind == tw.CAR_BASE)
    if car.any():
        glass = (kind == tw.CAR_CABIN) & ~top
        col = np.where(glass[:, None], np.array([0.02, 0.025, 0.035]), col)
        lab[car] = CAR
    tr = kind == tw.TRUNK
    lab[tr] = TRUNK
    return col, lab
