"""Exact ray casting against boxes, ellipsoids and the ground plane, through a uniform 2-D grid.

The grid covers the town in `cell` x `cell` metre columns; each column lists the boxes and
ellipsoids whose footprint touches it and the highest point in it. A ray walks the columns it
crosses in order (2-D DDA, Amanatides & Woo 1987), all rays of a batch at once (numpy, one loop
iteration per column step), tests only the primitives of its current column, and stops as soon
as its nearest hit lies inside the column (nothing later can be nearer), when it leaves the
grid, passes the ground plane, the distance cull, or rises above the tallest roof. So the cost
follows what a view sees, not the size of the town.

Robustness: a ray parallel to a slab is inside it or not by an explicit test (no 0 * inf NaN);
a ray that starts inside a box (a camera inside a building) sees the box's far faces from the
inside; a ray that starts on a face and leaves it does not hit that face (t must be > T_EPS).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

#: Smallest accepted hit distance (in units of the ray's direction length). Shadow rays also
#: start SHADOW_OFFSET metres off the surface, so this only rejects hits at the origin itself.
T_EPS = 1e-9
NONE = -1


#: Boxes no taller than this (sidewalk slabs, lawns) form their own layer, tested only where a ray
#: has come down to their height: they cover whole blocks, so most rays would test them in vain.
LOW_LAYER_M = 0.5


@dataclass
class Layer:
    """Column lists (CSR) of one group of primitives, with each column's highest point."""

    kind: int  # 0 boxes, 1 ellipsoids
    start: np.ndarray  # [nx*ny + 1] int64
    items: np.ndarray  # [K] int64 primitive ids
    col_zmax: np.ndarray  # [nx*ny] metres (-inf: empty column)


@dataclass
class Grid:
    """Uniform 2-D grid over the town: layers of column lists (low boxes, other boxes, ellipsoids)."""

    x0: float
    y0: float
    cell: float
    nx: int
    ny: int
    zmax: float
    layers: list[Layer]
    col_zmax: np.ndarray  # [nx*ny] highest point of anything in the column (m)


def _csr(lo: np.ndarray, hi: np.ndarray, x0: float, y0: float, cell: float, nx: int, ny: int):
    """Column lists for footprints lo..hi ([N, 2] each). Returns start [nx*ny+1], items, cells of each item."""
    ix0 = np.clip(np.floor((lo[:, 0] - x0) / cell).astype(np.int64), 0, nx - 1)
    ix1 = np.clip(np.floor((hi[:, 0] - x0) / cell).astype(np.int64), 0, nx - 1)
    iy0 = np.clip(np.floor((lo[:, 1] - y0) / cell).astype(np.int64), 0, ny - 1)
    iy1 = np.clip(np.floor((hi[:, 1] - y0) / cell).astype(np.int64), 0, ny - 1)
    cells, items = [], []
    for k in range(len(lo)):
        gx, gy = np.meshgrid(np.arange(ix0[k], ix1[k] + 1), np.arange(iy0[k], iy1[k] + 1), indexing="ij")
        c = (gy * nx + gx).ravel()
        cells.append(c)
        items.append(np.full(c.shape, k, dtype=np.int64))
    cells_a = np.concatenate(cells) if cells else np.zeros(0, np.int64)
    items_a = np.concatenate(items) if items else np.zeros(0, np.int64)
    order = np.lexsort((items_a, cells_a))  # stable, deterministic order inside a column
    cells_a, items_a = cells_a[order], items_a[order]
    start = np.zeros(nx * ny + 1, dtype=np.int64)
    np.add.at(start, cells_a + 1, 1)
    return np.cumsum(start), items_a, cells_a


def build_grid(box_lo, box_hi, ell_centre, ell_radii, cell: float = 8.0, margin: float = 2.0) -> Grid:
    """Grid over everything. box_lo/box_hi [N, 3]; ell_centre/ell_radii [M, 3]; cell in metres."""
    ell_lo, ell_hi = ell_centre - ell_radii, ell_centre + ell_radii
    all_lo = np.concatenate([box_lo, ell_lo]) if len(ell_lo) else box_lo
    all_hi = np.concatenate([box_hi, ell_hi]) if len(ell_hi) else box_hi
    x0, y0 = all_lo[:, 0].min() - margin, all_lo[:, 1].min() - margin
    nx = int(np.ceil((all_hi[:, 0].max() + margin - x0) / cell))
    ny = int(np.ceil((all_hi[:, 1].max() + margin - y0) / cell))
    colz = np.full(nx * ny, -np.inf)
    layers = []
    low = box_hi[:, 2] <= LOW_LAYER_M
    for kind, sel, lo, hi in ((0, np.nonzero(low)[0], box_lo, box_hi), (0, np.nonzero(~low)[0], box_lo, box_hi),
                              (1, np.arange(len(ell_lo)), ell_lo, ell_hi)):
        start, items, cells = _csr(lo[sel, :2], hi[sel, :2], x0, y0, cell, nx, ny)
        items = sel[items]  # back to primitive ids
        lz = np.full(nx * ny, -np.inf)
        np.maximum.at(lz, cells, hi[items, 2])
        colz = np.maximum(colz, lz)
        layers.append(Layer(kind, start, items, lz))
    return Grid(float(x0), float(y0), float(cell), nx, ny, float(all_hi[:, 2].max()), layers, colz)


def slab(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ray / axis-aligned box slab test, robust to zero direction components.

    Args:
        o, d: [P, 3] ray origins and directions.
        lo, hi: [P, 3] box corners.
    Returns:
        t_near, t_far [P]; axis_near, axis_far [P] (which slab bounds each).
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (lo - o) / d
        tb = (hi - o) / d
    tn = np.minimum(ta, tb)
    tf = np.maximum(ta, tb)
    par = d == 0.0
    if par.any():  # parallel to a slab: inside it (inclusive) for all t, or never
        inside = (o >= lo) & (o <= hi)
        tn = np.where(par, np.where(inside, -np.inf, np.inf), tn)
        tf = np.where(par, np.where(inside, np.inf, -np.inf), tf)
    an = np.argmax(tn, axis=1)
    af = np.argmin(tf, axis=1)
    r = np.arange(len(o))
    return tn[r, an], tf[r, af], an, af


def box_hit(o, d, lo, hi) -> np.ndarray:
    """Nearest hit t > T_EPS of rays [P, 3] with boxes [P, 3] (inf if none); from inside: the exit."""
    t_near, t_far, _, _ = slab(o, d, lo, hi)
    t = np.where(t_near > T_EPS, t_near, t_far)
    return np.where((t_near <= t_far) & (t > T_EPS), t, np.inf)


def ellipsoid_hit(o, d, c, r) -> np.ndarray:
    """Nearest hit t > T_EPS of rays [P, 3] with axis-aligned ellipsoids (centre c, radii r [P, 3])."""
    oc = (o - c) / r
    dd = d / r
    a = np.einsum("ij,ij->i", dd, dd)
    b = np.einsum("ij,ij->i", oc, dd)
    cc = np.einsum("ij,ij->i", oc, oc) - 1.0
    disc = b * b - a * cc
    sq = np.sqrt(np.maximum(disc, 0.0))
    t0 = (-b - sq) / a
    t1 = (-b + sq) / a
    t = np.where(t0 > T_EPS, t0, t1)
    return np.where((disc >= 0.0) & (t > T_EPS), t, np.inf)


def ground_hit(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """t where rays [R, 3] cross the plane z = 0 going towards it (inf otherwise)."""
    oz, dz = o[:, 2], d[:, 2]
    towards = ((oz > 0) & (dz < 0)) | ((oz < 0) & (dz > 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -oz / dz
    return np.where(towards & (t >= 0), t, np.inf)


def trace(grid: Grid, box_lo, box_hi, ell_c, ell_r, o: np.ndarray, d: np.ndarray, t_limit: np.ndarray,
          *, any_hit: bool = False, stats: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Nearest primitive hit along each ray, up to `t_limit`.

    Args:
        grid: acceleration structure over the primitives.
        box_lo, box_hi: [N, 3]; ell_c, ell_r: [M, 3].
        o, d: [R, 3] origins and directions (any length; t is in units of |d|).
        t_limit: [R] stop searching beyond this t (ground plane, distance cull).
        any_hit: stop at the first hit found (shadow rays); t is then some hit, not the nearest.
        stats: if given, counts "steps" (ray-column visits) and "tests" (ray-primitive tests).
    Returns:
        t [R] (inf: no primitive before t_limit) and prim [R] (box index, N + ellipsoid index, or -1).
    """
    R = len(o)
    n_box = len(box_lo)
    best_t = np.full(R, np.inf)
    best_p = np.full(R, NONE, dtype=np.int64)
    if R == 0:
        return best_t, best_p
    # 1. Clip each ray to the grid's bounding box (x, y) and the height range of the geometry.
    glo = np.array([grid.x0, grid.y0, -1.0])
    ghi = np.array([grid.x0 + grid.nx * grid.cell, grid.y0 + grid.ny * grid.cell, grid.zmax + 1e-6])
    t0, t1, _, _ = slab(o, d, np.broadcast_to(glo, o.shape), np.broadcast_to(ghi, o.shape))
    t0 = np.maximum(t0, 0.0)
    t1 = np.minimum(t1, t_limit)
    idx = np.nonzero(t0 < t1)[0]
    if idx.size == 0:
        return best_t, best_p
    # 2. DDA set-up for the rays that enter the grid.
    oo, dd = o[idx], d[idx]
    tc = t0[idx]
    tend = t1[idx]
    ix, iy, sx, sy, dtx, dty, tmx, tmy = _dda_start(grid, oo, dd, tc)
    blo = (box_lo[:, 0].copy(), box_lo[:, 1].copy(), box_lo[:, 2].copy())
    bhi = (box_hi[:, 0].copy(), box_hi[:, 1].copy(), box_hi[:, 2].copy())
    with np.errstate(divide="ignore"):
        inv = 1.0 / dd
    prims = _Prims(blo, bhi, bool((dd == 0).any()), ell_c, ell_r, n_box)
    steps = tests = 0
    # 3. Walk: one column per iteration for every live ray.
    for _ in range(grid.nx + grid.ny + 2):
        te = np.minimum(np.minimum(tmx, tmy), tend)
        cells = iy * grid.nx + ix
        # Height cull: skip the column if the ray's segment in it is above everything there.
        zlow = np.minimum(oo[:, 2] + tc * dd[:, 2], oo[:, 2] + te * dd[:, 2])
        lb = best_t[idx]
        tests += _column_hits(grid, cells, zlow, idx, oo, dd, inv, prims, lb, best_p)
        best_t[idx] = lb
        steps += len(idx)
        # A ray is finished if its nearest hit lies inside this column (or any hit, for
        # shadow rays), if it reached its limit, or if its next column is off the grid.
        if any_hit:
            done = np.isfinite(lb)
        else:
            done = lb <= te
        done |= te >= tend
        stepx = tmx <= tmy
        ix = np.where(stepx, ix + sx, ix)
        iy = np.where(stepx, iy, iy + sy)
        tmx = np.where(stepx, tmx + dtx, tmx)
        tmy = np.where(stepx, tmy, tmy + dty)
        done |= (ix < 0) | (ix >= grid.nx) | (iy < 0) | (iy >= grid.ny)
        keep = ~done
        if not keep.any():
            break
        idx, oo, dd, inv, tend = idx[keep], oo[keep], dd[keep], inv[keep], tend[keep]
        tc = te[keep]
        ix, iy, sx, sy, dtx, dty, tmx, tmy = (a[keep] for a in (ix, iy, sx, sy, dtx, dty, tmx, tmy))
    beyond = best_t > t_limit  # found in a column but past the ground / cull limit
    best_t[beyond] = np.inf
    best_p[beyond] = NONE
    if stats is not None:
        stats["steps"] = stats.get("steps", 0) + steps
        stats["tests"] = stats.get("tests", 0) + tests
    return best_t, best_p


class _Prims(NamedTuple):
    """The primitives `trace` tests: box corners per axis, ellipsoids, box count (ellipsoid ids follow)."""

    blo: tuple  # (x, y, z) arrays [N] of the boxes' low corners
    bhi: tuple
    has_par: bool  # some ray direction has a zero component
    ell_c: np.ndarray
    ell_r: np.ndarray
    n_box: int


def _dda_start(grid: Grid, oo, dd, tc):
    """2-D DDA state of rays entering the grid at t = tc: column (ix, iy), step direction (sx, sy),
    t per column crossed (dtx, dty) and t of the next column boundary (tmx, tmy)."""
    cs = grid.cell
    px = oo[:, 0] + tc * dd[:, 0]
    py = oo[:, 1] + tc * dd[:, 1]
    ix = np.clip(np.floor((px - grid.x0) / cs).astype(np.int64), 0, grid.nx - 1)
    iy = np.clip(np.floor((py - grid.y0) / cs).astype(np.int64), 0, grid.ny - 1)
    sx = np.where(dd[:, 0] > 0, 1, -1).astype(np.int64)
    sy = np.where(dd[:, 1] > 0, 1, -1).astype(np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        dtx = np.where(dd[:, 0] != 0, cs / np.abs(dd[:, 0]), np.inf)
        dty = np.where(dd[:, 1] != 0, cs / np.abs(dd[:, 1]), np.inf)
        nxb = grid.x0 + (ix + (sx > 0)) * cs  # next x boundary in the walking direction
        nyb = grid.y0 + (iy + (sy > 0)) * cs
        tmx = np.where(dd[:, 0] != 0, (nxb - oo[:, 0]) / dd[:, 0], np.inf)
        tmy = np.where(dd[:, 1] != 0, (nyb - oo[:, 1]) / dd[:, 1], np.inf)
    return ix, iy, sx, sy, dtx, dty, tmx, tmy


def _column_hits(grid: Grid, cells, zlow, idx, oo, dd, inv, pr: _Prims, lb, best_p) -> int:
    """Test the live rays `idx` against the primitives of their current columns `cells`, layer by
    layer (a layer only where the ray's lowest point `zlow` there is not above it); where a nearer
    hit is found, lower `lb` (their nearest t so far) and set `best_p`, in place.

    Returns:
        the number of ray-primitive tests.
    """
    ox, oy, oz = oo[:, 0], oo[:, 1], oo[:, 2]
    ivx, ivy, ivz = inv[:, 0], inv[:, 1], inv[:, 2]
    tests = 0
    for layer in grid.layers:
        start, items, kind = layer.start, layer.items, layer.kind
        s = start[cells]
        cnt = np.where(zlow <= layer.col_zmax[cells], start[cells + 1] - s, 0)
        tot = int(cnt.sum())
        if tot == 0:
            continue
        rep = np.repeat(np.arange(len(idx)), cnt)
        first = np.cumsum(cnt) - cnt
        offs = np.arange(tot) - np.repeat(first - s, cnt)
        prims = items[offs]
        if kind == 0:
            t = _box_pairs(ox, oy, oz, ivx, ivy, ivz, rep, prims, pr.blo, pr.bhi, pr.has_par)
        else:
            t = ellipsoid_hit(oo[rep], dd[rep], pr.ell_c[prims], pr.ell_r[prims])
            prims = prims + pr.n_box
        tests += tot
        nz = np.nonzero(cnt)[0]
        mins = np.minimum.reduceat(t, first[nz])
        better = mins < lb[nz]
        if better.any():
            rows = nz[better]
            lb[rows] = mins[better]
            is_min = (t == np.repeat(np.where(better, mins, -1.0), cnt[nz]))
            # Ties (coplanar faces) within a layer: the lowest primitive id wins.
            wr, wp = rep[is_min][::-1], prims[is_min][::-1]
            best_p[idx[wr]] = wp
    return tests


def _box_pairs(ox, oy, oz, ivx, ivy, ivz, rep, prims, blo, bhi, has_par: bool) -> np.ndarray:
    """`box_hit` for ray/box pairs, on per-axis arrays with precomputed 1/d (the hot loop).

    A ray's result depends only on that ray (not on the others in the batch), so views rendered
    together or alone give the same bits.
    """
    t_near = t_far = None
    for oa, iva, lo, hi in ((ox, ivx, blo[0], bhi[0]), (oy, ivy, blo[1], bhi[1]), (oz, ivz, blo[2], bhi[2])):
        orr, ivr = oa[rep], iva[rep]
        lo_p, hi_p = lo[prims], hi[prims]
        with np.errstate(invalid="ignore"):
            a = (lo_p - orr) * ivr
            b = (hi_p - orr) * ivr
        tn, tf = np.minimum(a, b), np.maximum(a, b)
        if has_par:  # direction component exactly 0: inside the slab for all t (inclusive), or never
            par = np.isinf(ivr)
            if par.any():
                inside = (orr >= lo_p) & (orr <= hi_p)
                tn = np.where(par, np.where(inside, -np.inf, np.inf), tn)
                tf = np.where(par, np.where(inside, np.inf, -np.inf), tf)
        t_near = tn if t_near is None else np.maximum(t_near, tn)
        t_far = tf if t_far is None else np.minimum(t_far, tf)
    t = np.where(t_near > T_EPS, t_near, t_far)
    return np.where((t_near <= t_far) & (t > T_EPS), t, np.inf)


def trace_brute(box_lo, box_hi, ell_c, ell_r, o, d, t_limit) -> tuple[np.ndarray, np.ndarray]:
    """Slow reference: every ray against every primitive (tests compare `trace` with this)."""
    R = len(o)
    best_t = np.full(R, np.inf)
    best_p = np.full(R, NONE, dtype=np.int64)
    n_box = len(box_lo)
    for k in range(n_box + len(ell_c)):
        if k < n_box:
            t = box_hit(o, d, np.broadcast_to(box_lo[k], o.shape), np.broadcast_to(box_hi[k], o.shape))
        else:
            j = k - n_box
            t = ellipsoid_hit(o, d, np.broadcast_to(ell_c[j], o.shape), np.broadcast_to(ell_r[j], o.shape))
        better = (t < best_t) & (t < t_limit)
        best_t[better] = t[better]
        best_p[better] = k
    return best_t, best_p
