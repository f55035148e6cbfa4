"""Render a town: RGB (sun, sky light, cast shadows, haze, supersampling), planar depth, labels.

`render(scene, camera)` is the whole pipeline for one image; `shade_rays` does the work for
any batch of rays (tests and benchmarks call it directly). Everything is float64 numpy with
elementwise arithmetic only (no BLAS), so results do not depend on the thread count.

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

from dataclasses import dataclass

import numpy as np

from ...cameras import Camera
from . import town as tw
from .trace import NONE, Grid, build_grid, ground_hit, slab, trace

LABELS = ("sky", "road", "road line", "sidewalk", "building", "roof", "vegetation", "trunk", "car", "terrain")
SKY, ROAD, LINE, SIDEWALK, BUILDING, ROOF, VEGETATION, TRUNK, CAR, TERRAIN = range(10)
#: Display colours of the labels (NOTE: Cityscapes/CARLA-like colours where a class exists there).
PALETTE = np.array([
    [70, 130, 180], [128, 64, 128], [157, 234, 50], [244, 35, 232], [70, 70, 70],
    [190, 100, 60], [107, 142, 35], [153, 153, 153], [0, 0, 142], [152, 251, 152],
], dtype=np.uint8)

SUN_RADIANCE = np.array([2.9, 2.75, 2.5])  # linear, warm
SKY_AMBIENT = np.array([0.42, 0.50, 0.62])  # linear, cool
SKY_ZENITH = np.array([0.16, 0.30, 0.62])
SKY_HORIZON = np.array([0.62, 0.70, 0.80])
HAZE = SKY_HORIZON
HAZE_M = 260.0  # e-folding distance of the haze, metres
EXPOSURE = 1.35  # NOTE: radiances, haze and exposure were tuned by eye on the gallery views
SHADOW_OFFSET = 1e-3  # m, shadow rays start this far off the surface (no self-shadowing)


@dataclass
class Scene:
    """A town prepared for rendering (geometry + grid)."""

    town: tw.Town
    grid: Grid
    cull_m: float = 220.0

    @classmethod
    def from_town(cls, town: tw.Town, cull_m: float = 220.0, cell: float = 12.0) -> "Scene":
        # NOTE: 12 m columns measured fastest on the small preset (8 m: +8 %, 16 m: +3 % CPU time).
        return cls(town, build_grid(town.box_lo, town.box_hi, town.ell_centre, town.ell_radii, cell), cull_m)


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


def surface(scene: Scene, o: np.ndarray, d: np.ndarray, t: np.ndarray, prim: np.ndarray, on_ground: np.ndarray):
    """Point, normal (facing the ray), albedo and label of hits.

    Args:
        o, d: [P, 3] rays; t [P] hit distances; prim [P] primitive ids (-1: ground plane hit).
        on_ground: [P] bool, the hit is the ground plane.
    Returns:
        p [P, 3], n [P, 3], albedo [P, 3], label [P] uint8.
    """
    town = scene.town
    P = len(t)
    p = o + t[:, None] * d
    n = np.zeros((P, 3))
    albedo = np.zeros((P, 3))
    label = np.zeros(P, dtype=np.uint8)
    # Ground plane.
    g = np.nonzero(on_ground)[0]
    if g.size:
        p[g, 2] = 0.0  # exactly on the plane: shading and shadow rays do not depend on rounding
        n[g, 2] = np.where(o[g, 2] >= 0, 1.0, -1.0)
        albedo[g], label[g] = ground_material(town, p[g, 0], p[g, 1])
    nb = len(town.box_lo)
    # Boxes.
    bsel = np.nonzero(~on_ground & (prim >= 0) & (prim < nb))[0]
    if bsel.size:
        n[bsel], p[bsel], albedo[bsel], label[bsel] = _box_surface(town, o[bsel], d[bsel], p[bsel], prim[bsel])
    # Ellipsoids (tree crowns).
    esel = np.nonzero(~on_ground & (prim >= nb))[0]
    if esel.size:
        j = prim[esel] - nb
        c, rr = town.ell_centre[j], town.ell_radii[j]
        pe = p[esel]
        ne = (pe - c) / (rr * rr)
        ne /= np.linalg.norm(ne, axis=1, keepdims=True)
        inside = np.einsum("ij,ij->i", ne, d[esel]) > 0
        ne[inside] *= -1
        n[esel] = ne
        leaf = 0.55 + 0.9 * vnoise(pe[:, 0] * 1.3 + pe[:, 2], pe[:, 1] * 1.3 - pe[:, 2], 0.5, 14)
        albedo[esel] = town.ell_colour[j] * leaf[:, None]
        label[esel] = VEGETATION
    return p, n, albedo, label


def _box_surface(town: tw.Town, ob: np.ndarray, db: np.ndarray, pb: np.ndarray, k: np.ndarray):
    """`surface` for hits [P] on boxes `k` along rays ob, db: normal, point pb snapped onto its face,
    albedo and label."""
    lo, hi = town.box_lo[k], town.box_hi[k]
    tn, tf, an, af = slab(ob, db, lo, hi)
    axis = np.where(tn > 1e-9, an, af)
    nn = np.zeros((len(k), 3))
    r = np.arange(len(k))
    nn[r, axis] = -np.sign(db[r, axis])
    nn[r, axis] = np.where(nn[r, axis] == 0, 1.0, nn[r, axis])
    # Snap the hit coordinate onto its face plane (textures read the exact face coordinate).
    enter = tn > 1e-9  # entering hits lie on the near face, hits from inside on the far one
    face = np.where(enter == (db[r, axis] > 0), lo[r, axis], hi[r, axis])
    pb[r, axis] = face
    top = (axis == 2) & (nn[r, 2] > 0)
    col, lab = _box_material(town, k, pb, lo, hi, axis, top)
    return nn, pb, col, lab


def _box_material(town: tw.Town, k, pb, lo, hi, axis, top):
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


def sky_colour(d: np.ndarray, sun: np.ndarray, clouds: float = 0.0) -> np.ndarray:
    """Linear sky radiance [P, 3] for world directions [P, 3]: horizon-to-zenith gradient, sun
    glow; with `clouds` > 0, clouds over it (`cloud_cover`)."""
    dn = d / np.linalg.norm(d, axis=1, keepdims=True)
    e = np.clip(dn[:, 2], 0.0, 1.0)
    col = SKY_HORIZON + (SKY_ZENITH - SKY_HORIZON) * np.sqrt(e)[:, None]
    glow = np.clip(np.einsum("ij,j->i", dn, sun), 0.0, 1.0) ** 24
    col = col + glow[:, None] * np.array([0.5, 0.45, 0.35])
    if clouds > 0:
        c = cloud_cover(dn, clouds)[:, None]
        col = col * (1.0 - c) + CLOUD * (0.8 + 0.2 * e)[:, None] * c
    return col


#: Cloud layer: height (m) and linear albedo under the sky's light.
CLOUD_HEIGHT_M = 1500.0
CLOUD = np.array([0.80, 0.80, 0.82])


def cloud_cover(dn: np.ndarray, cover: float) -> np.ndarray:
    """Cloud density [P] in [0, 1] seen in unit world directions dn [P, 3]: value noise on a
    layer at `CLOUD_HEIGHT_M` (three octaves, 900 / 350 / 120 m), thresholded so that about
    `cover` of the layer is cloud, thinning into the haze towards the horizon. A texture of the
    direction that no smooth function of it follows (the stiff towns' sky)."""
    up = dn[:, 2]
    s = CLOUD_HEIGHT_M / np.maximum(up, 0.05)
    x, y = dn[:, 0] * s, dn[:, 1] * s
    n = 0.5 * vnoise(x, y, 900.0, 11) + 0.3 * vnoise(x, y, 350.0, 12) + 0.2 * vnoise(x, y, 120.0, 13)
    lo = 1.0 - cover - 0.08
    r = np.clip((n - lo) / 0.2, 0.0, 1.0)
    return r * r * (3 - 2 * r) * np.clip(up / 0.08, 0.0, 1.0)


def _rows_times(v: np.ndarray, m: np.ndarray) -> np.ndarray:
    """v [P, 3] -> v @ m (m [3, 3]), elementwise (no BLAS: the same on any thread count)."""
    return v[:, 0:1] * m[0] + v[:, 1:2] * m[1] + v[:, 2:3] * m[2]


def shade_rays(scene: Scene, o: np.ndarray, d: np.ndarray, *, shadows: bool = True, stats: dict | None = None):
    """Trace and shade rays.

    Args:
        o, d: [R, 3] origins and directions. With camera-z = 1 directions, t is planar depth.
        shadows: cast shadow rays towards the sun.
        stats: optional counters (rays, shadow_rays, steps, tests).
    Returns:
        colour [R, 3] (tone-mapped, linear light, 0..1), t [R] (inf = sky), label [R] uint8,
        light [R] (sun visibility 0/1 times cos, for tests).
    """
    town = scene.town
    R = len(o)
    dnorm = np.linalg.norm(d, axis=1)
    d_world, sun, up = d, town.sun, np.array([0.0, 0.0, 1.0])
    if town.world is not None:  # a tilted town: trace in its own coordinates, light in the world's
        o, d = _rows_times(o, town.world), _rows_times(d, town.world)
        sun = _rows_times(town.sun[None], town.world)[0]
        up = town.world[2].copy()  # the world's up in town coordinates
    t_ground = ground_hit(o, d)
    t_cull = scene.cull_m / dnorm
    t_prim, prim = trace(scene.grid, town.box_lo, town.box_hi, town.ell_centre, town.ell_radii, o, d,
                         np.minimum(t_ground, t_cull), stats=stats)
    on_ground = np.isfinite(t_ground) & ~(t_prim <= t_ground)
    t = np.where(on_ground, t_ground, t_prim)
    hit = np.isfinite(t)
    colour = np.zeros((R, 3))
    label = np.zeros(R, dtype=np.uint8)
    light = np.zeros(R)
    hs = np.nonzero(hit)[0]
    sky = np.nonzero(~hit)[0]
    colour[sky] = sky_colour(d_world[sky], town.sun, town.clouds)
    if hs.size:
        p, n, albedo, lab = surface(scene, o[hs], d[hs], t[hs], prim[hs], on_ground[hs])
        label[hs] = lab
        cos = np.einsum("ij,j->i", n, sun)
        vis = (cos > 0).astype(np.float64)
        if shadows:
            lit = np.nonzero(cos > 0)[0]
            so = p[lit] + SHADOW_OFFSET * n[lit]
            sd = np.broadcast_to(sun, so.shape).copy()
            ts, _ = trace(scene.grid, town.box_lo, town.box_hi, town.ell_centre, town.ell_radii, so, sd,
                          np.full(len(lit), scene.cull_m), any_hit=True, stats=stats)
            vis[lit] = np.where(np.isfinite(ts), 0.0, 1.0)
            if stats is not None:
                stats["shadow_rays"] = stats.get("shadow_rays", 0) + len(lit)
        direct = np.maximum(cos, 0.0) * vis
        light[hs] = direct
        ambient = 0.55 + 0.45 * (n[:, 0] * up[0] + n[:, 1] * up[1] + n[:, 2] * up[2])  # sky light: full from above, half from the side
        radiance = albedo * (direct[:, None] * SUN_RADIANCE + ambient[:, None] * SKY_AMBIENT)
        dist = t[hs] * dnorm[hs]
        fog = 1.0 - np.exp(-dist / HAZE_M)
        ramp = np.clip((dist - 0.6 * scene.cull_m) / (0.4 * scene.cull_m), 0.0, 1.0)
        fog = np.maximum(fog, ramp * ramp * (3 - 2 * ramp))  # fully hazed at the cull radius
        colour[hs] = radiance * (1 - fog)[:, None] + HAZE * fog[:, None]
    if stats is not None:
        stats["rays"] = stats.get("rays", 0) + R
    colour = 1.0 - np.exp(-EXPOSURE * colour)  # soft tone curve, per sample (before averaging)
    return colour, t, label, light


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> sRGB [0, 1] (IEC 61966-2-1 transfer function)."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def sample_offsets(aa: int) -> np.ndarray:
    """Sub-pixel offsets [S, 2] from the pixel centre; row 0 is the centre itself."""
    if aa <= 1:
        return np.zeros((1, 2))
    g = (np.arange(aa) + 0.5) / aa - 0.5
    grid = np.stack(np.meshgrid(g, g, indexing="xy"), axis=-1).reshape(-1, 2)
    if aa % 2 == 1:  # the centre is on the grid: put it first
        c = np.argmin(np.abs(grid).sum(1))
        return np.concatenate([grid[c:c + 1], np.delete(grid, c, axis=0)])
    return np.concatenate([np.zeros((1, 2)), grid])


def camera_rays(camera: Camera, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Origins and directions [S*H*W, 3] (sample-major) with camera z = 1 (t = planar depth)."""
    K, c2w = camera.K, camera.c2w
    H, W = camera.height, camera.width
    j, i = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    u = (j.ravel()[None, :] + 0.5 + offsets[:, :1]).ravel()
    v = (i.ravel()[None, :] + 0.5 + offsets[:, 1:]).ravel()
    x = (u - K[0, 2]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    R = c2w[:3, :3]
    d = x[:, None] * R[:, 0] + y[:, None] * R[:, 1] + R[:, 2]  # elementwise: no BLAS, thread-count free
    o = np.broadcast_to(c2w[:3, 3], d.shape).copy()
    return o, d


def _needs_more_samples(colour: np.ndarray, t: np.ndarray, label: np.ndarray, threshold: float) -> np.ndarray:
    """Pixels [H, W] whose centre sample differs from a 4-neighbour's: another label, a depth jump
    of over 5 %, or a colour step over `threshold` (edges, shadow borders, fine texture)."""
    flag = np.zeros(label.shape, dtype=bool)
    logt = np.log(np.where(np.isfinite(t), t, 1e6))
    for ax in (0, 1):
        diff = np.diff(label.astype(np.int16), axis=ax) != 0
        diff |= np.abs(np.diff(logt, axis=ax)) > 0.05
        diff |= np.abs(np.diff(colour, axis=ax)).max(axis=-1) > threshold
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[ax], hi[ax] = slice(0, -1), slice(1, None)
        flag[tuple(lo)] |= diff
        flag[tuple(hi)] |= diff
    return flag


def render(scene: Scene, camera: Camera, aa: int = 2, *, adaptive: bool = True, shadows: bool = True,
           stats: dict | None = None):
    """Render one view.

    Supersampling is adaptive: every pixel gets its centre ray; pixels that differ from a neighbour
    (see `_needs_more_samples`) get the other `sample_offsets(aa)` rays too, and their colour is the
    mean of all their samples in linear light. With adaptive=False every pixel gets every sample.

    Returns:
        rgb float32 [H, W, 3] sRGB in [0, 1]; depth float32 [H, W] planar metres (inf = sky);
        labels uint8 [H, W].
    """
    return render_batch(scene, [camera], aa, adaptive=adaptive, shadows=shadows, stats=stats)[0]


def render_batch(scene: Scene, cameras: list[Camera], aa: int = 2, *, adaptive: bool = True,
                 shadows: bool = True, stats: dict | None = None) -> list[tuple]:
    """`render` for several views at once (their rays share one traversal: less per-call overhead
    for small images). Every view's pixels are computed exactly as `render` alone would."""
    offs = sample_offsets(aa)
    sizes = [c.height * c.width for c in cameras]
    first = [camera_rays(c, offs[:1]) for c in cameras]
    o = np.concatenate([f[0] for f in first])
    d = np.concatenate([f[1] for f in first])
    colour, t, label, _ = shade_rays(scene, o, d, shadows=shadows, stats=stats)
    out = []
    base = 0
    for cam, n in zip(cameras, sizes):
        H, W = cam.height, cam.width
        out.append([colour[base:base + n].reshape(H, W, 3), t[base:base + n].reshape(H, W).astype(np.float32),
                    label[base:base + n].reshape(H, W)])
        base += n
    if len(offs) > 1:
        extra_o, extra_d, where = [], [], []
        for k, (cam, (c, dep, lab)) in enumerate(zip(cameras, out)):
            H, W = cam.height, cam.width
            flag = _needs_more_samples(c, dep, lab, 0.08) if adaptive else np.ones((H, W), dtype=bool)
            pix = np.nonzero(flag.ravel())[0]
            if pix.size:
                o2, d2 = camera_rays(cam, offs[1:])
                sel = (np.arange(len(offs) - 1)[:, None] * (H * W) + pix[None, :]).ravel()
                extra_o.append(o2[sel])
                extra_d.append(d2[sel])
                where.append((k, pix))
            if stats is not None:
                stats["supersampled_pixels"] = stats.get("supersampled_pixels", 0) + int(pix.size)
        if where:
            c2, _, _, _ = shade_rays(scene, np.concatenate(extra_o), np.concatenate(extra_d), shadows=shadows, stats=stats)
            base = 0
            for k, pix in where:
                m = (len(offs) - 1) * len(pix)
                part = c2[base:base + m].reshape(len(offs) - 1, len(pix), 3)
                base += m
                flat = out[k][0].reshape(-1, 3)
                flat[pix] = (flat[pix] + part.sum(axis=0)) / len(offs)
    return [(srgb_encode(c).astype(np.float32), dep, lab) for c, dep, lab in out]


def colourise_labels(labels: np.ndarray) -> np.ndarray:
    """uint8 [H, W] labels -> uint8 [H, W, 3] palette colours."""
    return PALETTE[np.minimum(labels, len(PALETTE) - 1)]
