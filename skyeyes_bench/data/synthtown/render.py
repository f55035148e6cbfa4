"""Render a town: RGB (sun, sky light, cast shadows, haze, supersampling), planar depth, labels.

`render(scene, camera)` is the whole pipeline for one image; `shade_rays` does the work for
any batch of rays (tests and benchmarks call it directly). Everything is float64 numpy with
elementwise arithmetic only (no BLAS), so results do not depend on the thread count.

The semantic labels (`LABELS`, `PALETTE`: their ids and display colours), the value noise and
the surfaces' materials live in `materials` (names kept importable from here).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...cameras import Camera
from . import town as tw
from .materials import (  # noqa: F401  (LABELS, PALETTE, the label ids, colourise_labels: importable from here too)
    BUILDING, CAR, LABELS, LINE, PALETTE, ROAD, ROOF, SIDEWALK, SKY, TERRAIN, TRUNK, VEGETATION, box_material,
    colourise_labels, ground_material, vnoise,
)
from .trace import NONE, Grid, build_grid, ground_hit, slab, trace

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
    col, lab = box_material(town, k, pb, lo, hi, axis, top)
    return nn, pb, col, lab


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
