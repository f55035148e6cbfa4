"""Benchmarks of the CPU Gaussian splatting (issue 6). Prints figures; not a test.

    python bench/gaussians.py raster            # fwd / fwd+bwd ms, peak RSS, load average
    python bench/gaussians.py raster --sizes 128 --counts 50000
    python bench/gaussians.py split --sizes 128 --counts 50000   # the stages of one call apart
    python bench/gaussians.py fit --preset small   # held-out aerial / ground PSNR vs seconds
    python bench/gaussians.py fit --preset small --data DIR   # another dataset's validation split

`fit` chooses schedules, so it runs on the validation split (docs/evaluate.md, "The split"; --split test exits 2):
the first validation lane of --data (default: the SynthTown validation data of --preset,
`skyeyes-bench data synthtown --preset P --split val`, made if absent), the colours learned on
what a run on that split trains on.

Caveat: the machine has 2 cores shared with other jobs; figures vary by tens of percent.
Peak RSS is the process's high-water mark (resource.getrusage), so run one case per process
(`--counts N --sizes S`) to attribute it to that case; the default loop runs each case in a
fresh subprocess for that reason.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time

from reference import screen


def synthetic_scene(n: int, size: int, overlap: float = 150.0, seed: int = 0):
    """n Gaussians in front of a 90-degree camera, sized so ~`overlap` cover each pixel."""
    import torch

    g = torch.Generator().manual_seed(seed)
    f = size / 2.0  # 90 degree horizontal fov
    z = 4.0 + 2.0 * torch.rand(n, generator=g)
    x = (torch.rand(n, generator=g) * 2 - 1) * z
    y = (torch.rand(n, generator=g) * 2 - 1) * z
    means = torch.stack([x, y, z], -1)
    # Support area pi * 9 * sigma^2 per Gaussian (3-sigma ellipse) -> sigma in px for `overlap`.
    sigma_px = math.sqrt(overlap * size * size / n / (9 * math.pi))
    scales = (sigma_px * z / f)[:, None] * (0.7 + 0.6 * torch.rand(n, 3, generator=g))
    quats = torch.randn(n, 4, generator=g)
    opac = 0.05 + 0.5 * torch.rand(n, generator=g)
    sh = 0.3 * torch.randn(n, 16, 3, generator=g)
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    return means, quats, scales, opac, sh, torch.eye(4), K


def raster_case(n: int, size: int, reps: int, threads: int) -> dict:
    import torch

    torch.set_num_threads(threads)
    from reference.common.gaussians import rasterize
    from reference.common.gaussians import raster
    from reference.common.gaussians.project import project

    means, quats, scales, opac, sh, view, K = synthetic_scene(n, size)
    proj = project(means, quats, scales, view, K, size, size)
    # (pixel, Gaussian) pairs the compositing evaluates per pixel before early stop: what the
    # tile binning costs (the 3-sigma overlap per pixel is the lower bound).
    ids, starts, _, _ = raster.bin_tiles(proj["means2d"], proj["radii"], proj["depths"], proj["valid"], size, size,
                                         raster.TILE, conics=proj["conics"], opacities=opac)
    pairs_per_px = len(ids) * raster.TILE ** 2 / (size * size)
    c = proj["conics"]
    det = (c[:, 0] * c[:, 2] - c[:, 1] ** 2).clamp_min(1e-12)
    overlap = float((9 * math.pi / det.sqrt())[proj["valid"]].sum()) / (size * size)
    params = [t.clone().requires_grad_() for t in (means, quats, scales, opac, sh)]
    fwd, both = [], []
    for r in range(reps + 1):
        t0 = time.perf_counter()
        with torch.no_grad():
            rasterize(*params, view, K, size, size)
        t1 = time.perf_counter()
        out = rasterize(*params, view, K, size, size)
        (out["rgb"].sum() + out["alpha"].sum()).backward()
        t2 = time.perf_counter()
        if r:  # first repetition warms up allocator and threads
            fwd.append(t1 - t0)
            both.append(t2 - t1)
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"n": n, "size": size, "overlap_per_px": round(overlap, 1), "tile_pairs_per_px": round(pairs_per_px, 1),
            "fwd_ms": round(1000 * min(fwd), 1), "fwd_bwd_ms": round(1000 * min(both), 1),
            "peak_rss_mb": round(rss_mb), "threads": torch.get_num_threads(), "load": round(os.getloadavg()[0], 1)}


def cmd_raster(args) -> None:
    if args.one:
        print(json.dumps(raster_case(args.counts[0], args.sizes[0], args.reps, args.threads)))
        return
    print("Reference prototype (issue 6): 50k@128 fwd+bwd 364 ms / 1.1 GB; 200k@256 2.26 s / 3.8 GB")
    print(f"threads {args.threads}; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print(f"{'N':>7} {'size':>5} {'overlap/px':>10} {'pairs/px':>8} {'fwd ms':>8} {'fwd+bwd ms':>10} {'peak RSS MB':>11} {'load':>5}")
    for size in args.sizes:
        for n in args.counts:
            cmd = [sys.executable, __file__, "raster", "--one", "--counts", str(n), "--sizes", str(size),
                   "--reps", str(args.reps), "--threads", str(args.threads)]
            r = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.strip().splitlines()[-1])
            print(f"{r['n']:>7} {r['size']:>5} {r['overlap_per_px']:>10} {r['tile_pairs_per_px']:>8} {r['fwd_ms']:>8} "
                  f"{r['fwd_bwd_ms']:>10} {r['peak_rss_mb']:>11} {r['load']:>5}")


def split_case(n: int, size: int, reps: int, threads: int) -> dict:
    """Stages of one `rasterize` call timed apart (ms, min over `reps` after a warm-up): projection,
    SH colours, binning, compositing forward, compositing backward, projection + SH backward."""
    import torch

    torch.set_num_threads(threads)
    from reference.common.gaussians import raster
    from reference.common.gaussians.project import project, sh_colors

    means, quats, scales, opac, sh, view, K = synthetic_scene(n, size)
    names = ["project", "sh", "bin", "composite_fwd", "composite_bwd", "project_sh_bwd"]
    rows = []
    for r in range(reps + 1):
        m, q, s, o, h = (t.clone().requires_grad_() for t in (means, quats, scales, opac, sh))
        t = [time.perf_counter()]
        proj = project(m, q, s, view, K, size, size)
        t.append(time.perf_counter())
        feats = torch.cat([sh_colors(h, m, view, 3), proj["depths"][:, None]], -1)
        t.append(time.perf_counter())
        ids, starts, tx, _ = raster.bin_tiles(proj["means2d"], proj["radii"], proj["depths"], proj["valid"], size,
                                             size, raster.TILE, conics=proj["conics"], opacities=o)
        t.append(time.perf_counter())
        out, alpha = raster.composite(proj["means2d"], proj["conics"], o, feats, torch.zeros(4), ids, starts, tx,
                                      size, size)
        t.append(time.perf_counter())
        inputs = [proj["means2d"], proj["conics"], feats]
        grads = torch.autograd.grad(out[..., :3].sum() + alpha.sum(), inputs + [o])
        t.append(time.perf_counter())
        torch.autograd.backward(inputs, grads[:3])
        t.append(time.perf_counter())
        if r:  # the first call warms up allocator and threads
            rows.append([b - a for a, b in zip(t, t[1:])])
    best = [1000 * min(col) for col in zip(*rows)]
    return {"n": n, "size": size, "threads": threads, **{k: round(v, 1) for k, v in zip(names, best)},
            "sum": round(sum(best), 1), "load": round(os.getloadavg()[0], 1)}


def cmd_split(args) -> None:
    for size in args.sizes:
        for n in args.counts:
            print(json.dumps(split_case(n, size, args.reps, args.threads)), flush=True)


def fit_curve(preset: str, method: str = "gaussians3d", *, data: str | None = None, seconds: float | None = None,
              workdir: str | None = None, overrides: list[str] | tuple = (), split: str = "val") -> list[dict]:
    """Held-out aerial PSNR and ground-view PSNR against training seconds, for the first
    validation scene of `data` (default: SynthTown's validation data of the preset). Prints one
    line per training checkpoint. `overrides`: `--set` strings on top of the preset (every 8th
    aerial view is held out). `split`: val (test is refused: `screen.screen_data`)."""
    from skyeyes_bench.splits import screening_split

    screening_split(split, "bench/gaussians.py fit")  # before anything is imported, made or read
    import tempfile
    from pathlib import Path

    import numpy as np
    import torch

    from reference.common.gaussians.train import psnr
    from reference.methods import get_method_class

    cls = get_method_class(method)
    config, _ = cls.configure(preset, ["holdout_every=8", *overrides])  # checked before any data is made
    ds = screen.screen_data(split, "bench/gaussians.py fit", data=data,
                            preset=preset if preset in ("smoke", "small", "paper") else "small")
    scene = ds.split("test")[0]
    m = cls(config, Path(workdir or tempfile.mkdtemp(prefix="gs-curve-")), progress=False)
    m.fit_train(ds)  # the learned colour map and backgrounds, as reproduce does
    aerial = list(scene.aerial)
    held = [f for i, f in enumerate(aerial) if i % 8 == 7]
    ground = [f for s in scene.sequences.values() for f in s.frames[::4]]
    rows: list[dict] = []
    print(f"scene {scene.name}: {len(aerial) - len(held)} train / {len(held)} held-out aerial views, "
          f"{len(ground)} ground frames scored; method {method}, preset {preset}")
    print(f"{'iter':>6} {'train s':>8} {'gaussians':>9} {'aerial PSNR':>11} {'ground PSNR':>11}")

    def cb(it, secs, model):
        if seconds is not None and secs > seconds:
            return

        def score(frames, ground_view):
            return np.mean([psnr(torch.from_numpy(m.render_frame(scene, f, ground=ground_view, model=model)),
                                 torch.from_numpy(f.image())) for f in frames])

        pa, pg = score(held, False), score(ground, True)
        rows.append({"iteration": it, "train_s": secs, "gaussians": len(model), "aerial_psnr": pa, "ground_psnr": pg})
        print(f"{it:>6} {secs:>8.1f} {len(model):>9} {pa:>11.2f} {pg:>11.2f}", flush=True)

    m.use_threads()  # as fit_one_scene would; the model is not checkpointed: a curve, not a fit to keep
    m.fit_scene_model(scene, progress=False, callback=cb)
    return rows


def cmd_fit(args) -> None:
    fit_curve(args.preset, args.method, data=args.data, seconds=args.seconds, overrides=args.overrides,
              split=args.split)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("raster")
    r.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    r.add_argument("--counts", type=int, nargs="+", default=[10_000, 50_000, 200_000])
    r.add_argument("--reps", type=int, default=3)
    r.add_argument("--threads", type=int, default=1, help="torch threads (1: see docs/reproduce.md)")
    r.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    r.set_defaults(fn=cmd_raster)
    sp = sub.add_parser("split", help="time the stages of one rasterize call apart")
    sp.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    sp.add_argument("--counts", type=int, nargs="+", default=[50_000, 200_000])
    sp.add_argument("--reps", type=int, default=7)
    sp.add_argument("--threads", type=int, default=1)
    sp.set_defaults(fn=cmd_split)
    f = sub.add_parser("fit")
    f.add_argument("--preset", default="smoke")
    f.add_argument("--method", default="gaussians3d")
    screen.split_options(f)
    f.add_argument("--seconds", type=float, default=None, help="stop reporting after this many training seconds")
    f.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    f.set_defaults(fn=cmd_fit)
    args = p.parse_args(argv)
    args.fn(args)


if __name__ == "__main__":
    screen.run_main(main, sys.argv[1:])
