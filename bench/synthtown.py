"""SynthTown renderer benchmark: rays/s, images/s per preset, paper-preset estimate, 1x vs 4x town.

    .venv/bin/python bench/synthtown.py [--quick]

Prints figures; times are wall clock and process CPU (the machine may be shared: CPU seconds are
the steadier number). Work counters (ray-column steps, ray-primitive tests) do not depend on load.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from skyeyes_bench.data.synthtown import PRESETS
from skyeyes_bench.data.synthtown import town as tw
from skyeyes_bench.data.synthtown.generate import lane_cameras, plan
from skyeyes_bench.data.synthtown.render import Scene, render


def tiled(t: tw.Town, n: int) -> tw.Town:
    """The town repeated n x n times (n^2 the area); the original stays at its place (tile 0, 0)."""
    px, py = t.xs[-1] - t.xs[0], t.ys[-1] - t.ys[0]
    nb = len(t.bld["x0"])
    lo, hi, kind, obj, col, ec, er, ecol = [], [], [], [], [], [], [], []
    bld = {k: [] for k in t.bld}
    for i in range(n):
        for j in range(n):
            off = np.array([i * px, j * py, 0.0])
            k = i * n + j
            lo.append(t.box_lo + off)
            hi.append(t.box_hi + off)
            kind.append(t.box_kind)
            obj.append(np.where(t.box_obj >= 0, t.box_obj + k * nb, -1))
            col.append(t.box_colour)
            ec.append(t.ell_centre + off)
            er.append(t.ell_radii)
            ecol.append(t.ell_colour)
            for key, v in t.bld.items():
                bld[key].append(v + (off[0] if key == "x0" else off[1] if key == "y0" else 0))
    xs = np.concatenate([t.xs] + [t.xs[1:] + i * px for i in range(1, n)])
    ys = np.concatenate([t.ys] + [t.ys[1:] + j * py for j in range(1, n)])
    return tw.Town(name=t.name + f"-x{n * n}", seed=t.seed, xs=xs, ys=ys, box_lo=np.concatenate(lo),
                   box_hi=np.concatenate(hi), box_kind=np.concatenate(kind), box_obj=np.concatenate(obj),
                   box_colour=np.concatenate(col), bld={k: np.concatenate(v) for k, v in bld.items()},
                   ell_centre=np.concatenate(ec), ell_radii=np.concatenate(er), ell_colour=np.concatenate(ecol),
                   sun=t.sun, params=dict(t.params))


def run(scene: Scene, cams, aa: int) -> dict:
    stats: dict = {}
    w0, c0 = time.perf_counter(), time.process_time()
    for cam in cams:
        render(scene, cam, aa, stats=stats)
    stats["wall_s"] = time.perf_counter() - w0
    stats["cpu_s"] = time.process_time() - c0
    stats["images"] = len(cams)
    return stats


def per_preset(name: str, n_ground: int, n_aerial: int, size: int | None = None) -> None:
    p = PRESETS[name] if size is None else replace(PRESETS[name], width=size, height=size)
    entry = plan(p, 0)[-1]  # the test town
    scene = Scene.from_town(entry["town"], cull_m=p.cull_m)
    ground, aerial = lane_cameras(entry["lanes"][0], p)
    pick = np.linspace(0, len(ground) - 1, n_ground).astype(int)
    cams = [ground[i][2] for i in pick] + [a[2] for a in aerial[:n_aerial]]
    s = run(scene, cams, p.aa)
    rays = s["rays"] + s.get("shadow_rays", 0)
    total = sum(n for _, n in p.lanes) * p.frames * 8 + sum(n for _, n in p.lanes) * len(range(0, p.frames, p.aerial_stride)) * p.aerial_yaws
    ips_cpu = s["images"] / s["cpu_s"]
    print(f"{name:6s} {p.width}x{p.height} aa={p.aa}: {s['images']} images, {s['rays']} camera + "
          f"{s.get('shadow_rays', 0)} shadow rays; {rays / s['cpu_s'] / 1e3:.0f} k rays/s/core (CPU), "
          f"{ips_cpu:.2f} images/s/core (CPU), {s['images'] / s['wall_s']:.2f} images/s (wall); "
          f"preset has {total} images -> about {total / ips_cpu / 60:.1f} CPU-minutes")


def town_scaling(n_views: int) -> None:
    p = PRESETS["small"]
    t1 = tw.make_town("test-0", 0, p.blocks)
    lane = tw.make_lanes(t1, 1, p.frames, p.step_m, 0)[0]
    ground, aerial = lane_cameras(lane, p)
    cams = [ground[i][2] for i in np.linspace(0, len(ground) - 1, n_views).astype(int)] + [a[2] for a in aerial[::max(1, len(aerial) // 4)]]
    out = {}
    for n in (1, 2):
        scene = Scene.from_town(t1 if n == 1 else tiled(t1, n), cull_m=p.cull_m)
        run(scene, cams[:1], p.aa)  # warm-up
        out[n] = s = run(scene, cams, p.aa)
        print(f"town {n * n}x area ({len(scene.town.box_lo)} boxes, {len(scene.town.ell_centre)} crowns): "
              f"{s['cpu_s']:.2f} s CPU, {s['wall_s']:.2f} s wall for {s['images']} views; "
              f"{s['steps']} column steps, {s['tests']} primitive tests")
    r_cpu = out[2]["cpu_s"] / out[1]["cpu_s"]
    r_work = (out[2]["steps"] + out[2]["tests"]) / (out[1]["steps"] + out[1]["tests"])
    print(f"4x / 1x town, same lane and views: CPU time x{r_cpu:.2f}, work (steps + tests) x{r_work:.2f} (target < 1.3)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer views")
    a = ap.parse_args()
    k = 1 if a.quick else 2
    per_preset("smoke", 16 * k, 4 * k)
    per_preset("small", 8 * k, 4 * k)
    per_preset("paper", 1 * k, 1 * k)
    town_scaling(8 * k)


if __name__ == "__main__":
    main()
