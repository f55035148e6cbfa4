"""Cost and behaviour of the depth-based metrics' geometry (docs/metrics.md): seen masks of every
ground frame of one lane against all its aerial views, the warps of consecutive frames, the
unseen share per depth tolerance, and the ground truth's warp floor, on a validation lane (a
tolerance is chosen here, never on test: docs/evaluate.md, "The split"; --split test exits 2).

    nice -n 19 .venv/bin/python bench/depth_metrics.py [--preset small] [--data DIR] [--scene val-0-lane00] [--tols 0.005,0.01,0.02,0.05]

The data is --data (default: the SynthTown validation data of --preset, `skyeyes-bench data
synthtown --preset P --split val`, made if absent) as a run on its validation split sees it; the
lane is --scene, one of its validation scenes (default: the first).
Prints the machine's load average before and after (the figures scale with it on a shared CPU).
Computes directly (no mask cache), single process.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from reference import screen
from skyeyes_bench.errors import UserError
from skyeyes_bench.metrics.geometry import seen_mask, warp_coords, warp_error


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    screen.split_options(ap)
    ap.add_argument("--preset", default="small", help="the SynthTown preset of the default data (default small)")
    ap.add_argument("--scene", default=None, help="a validation scene (default: the first)")
    ap.add_argument("--tols", default="0.005,0.01,0.02,0.05")
    ap.add_argument("--frames", type=int, default=0, help="only the first N ground frames (0: all)")
    args = ap.parse_args(argv)
    ds = screen.screen_data(args.split, "bench/depth_metrics.py", data=args.data, preset=args.preset)
    scenes = {s.name: s for s in ds.split("test")}  # the validation scenes (`screen_data`)
    if args.scene is not None and args.scene not in scenes:
        raise UserError(f"--scene {args.scene}: not a {ds.scored} scene of {ds.name} ({', '.join(scenes)})")
    scene = scenes[args.scene] if args.scene else next(iter(scenes.values()))
    frames = [f for q in scene.sequences.values() for f in q.frames]
    if args.frames:
        frames = frames[:args.frames]
    print(f"{ds.name} {scene.name} ({ds.scored} split): {len(frames)} ground frames {frames[0].width}x"
          f"{frames[0].height}, {len(scene.aerial)} aerial views {scene.aerial[0].width}x{scene.aerial[0].height}; "
          f"load average {os.getloadavg()[0]:.1f}, {os.cpu_count()} cores")
    t0 = time.perf_counter()
    cams = [a.camera() for a in scene.aerial]
    adepths = np.stack([a.depth() for a in scene.aerial])
    gdepths = [f.depth() for f in frames]
    gcams = [f.camera() for f in frames]
    print(f"read depth + poses: {time.perf_counter() - t0:.2f} s")
    for tol in (float(t) for t in args.tols.split(",")):
        t0 = time.perf_counter()
        seen = np.stack([seen_mask(d, c, adepths, cams, tol) for d, c in zip(gdepths, gcams)])
        dt = time.perf_counter() - t0
        sky = np.stack([np.isposinf(d) for d in gdepths])
        print(f"tol {tol}: seen masks {dt:.2f} s ({1000 * dt / len(frames):.1f} ms/frame); unseen share "
              f"{1 - seen.mean():.4f} (sky {sky.mean():.4f}, sky seen {seen[sky].mean() if sky.any() else 0:.4f}; "
              f"unseen surfaces {(~seen & ~sky).mean():.4f})")
    t0 = time.perf_counter()
    errs, counts = [], []
    for q in scene.sequences.values():
        fs = list(q.frames)
        for a, b in zip(fs[:-1], fs[1:]):
            uv, valid = warp_coords(b.depth(), b.camera(), a.depth(), a.camera(), 0.01)
            e, n = warp_error(a.image(), b.image(), uv, valid)
            errs.append(e)
            counts.append(n)
    dt = time.perf_counter() - t0
    e, n = np.array(errs), np.array(counts, float)
    print(f"warps (tol 0.01, incl. reading frames): {dt:.2f} s ({1000 * dt / len(errs):.1f} ms/pair); valid "
          f"pixels {n.sum() / (len(errs) * frames[0].width * frames[0].height):.3f}; ground-truth floor "
          f"{np.nansum(e * n) / n.sum():.4f}")
    print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    screen.run_main(main, sys.argv[1:])
