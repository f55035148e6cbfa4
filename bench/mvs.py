"""Depth accuracy and run time of the `mvs` stereo against SynthTown's true aerial depth, on the
validation lanes (settings are chosen here, never on test: docs/evaluate.md, "The split"; --split test exits 2).

    python bench/mvs.py                      # presets smoke and small, every validation lane
    python bench/mvs.py --presets small --set planes=128 --lanes 1
    python bench/mvs.py --presets small --data DIR   # another dataset's validation split (its
                                             # protocol's val.toml: own towns or a part of train)
    python bench/mvs.py figure --runs outputs/mvs-small outputs/gaussians3d-small outputs/sugar-small \
        --out docs/img/reconstructions-small.png        # ground truth beside each run's frames

The data is each preset's SynthTown validation data (`skyeyes-bench data synthtown --preset P
--split val`, made if absent), or --data (one preset) seen as a run on its validation split sees
it. `figure` shows the frames of the split each run scored (its config.json).

Per preset and lane: seconds of `reconstruct` (plane sweep, consistency, fusion), and over the
aerial pixels whose true surface lies inside the lane's region box (what the ground cameras can
see; sky and the town beyond are not asked for):

- abs rel: mean and median of |d - d*| / d* over pixels with a kept depth,
- within 0.5 m: share of kept depths within 0.5 m of the truth (a SynthTown small aerial pixel
  spans ~1.1 m at 70 m, so this is a sub-pixel test),
- within 2%: share within 2% (the consistency test's tolerance),
- completeness: share of the region's pixels that kept a depth,
- points: fused points in the region.

Depths are planar (camera z), as the EXR layers. Prints a markdown table; `--json FILE` also
writes the rows.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import numpy as np

from reference import screen
from skyeyes_bench.errors import UserError
from skyeyes_bench.splits import screening_split


def depth_errors(est: np.ndarray, truth: np.ndarray, inside: np.ndarray) -> dict:
    """Errors of est [H, W] (NaN = none) against truth [H, W] on the `inside` mask."""
    ok = inside & np.isfinite(est)
    rel = np.abs(est[ok] - truth[ok]) / truth[ok]
    ab = np.abs(est[ok] - truth[ok])
    return {"n": int(ok.sum()), "n_inside": int(inside.sum()), "rel": rel, "abs": ab}


def inside_region(frame, box: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(true depth [H, W], mask of pixels whose true surface point lies in `box`)."""
    truth = frame.depth()
    if truth is None:
        raise UserError(f"{frame.path}: no depth layer (bench/mvs.py needs SynthTown's aerial depth)")
    cam = frame.camera()
    h, w = truth.shape
    v, u = np.mgrid[0:h, 0:w] + 0.5
    finite = np.isfinite(truth)
    pts = cam.unproject(np.stack([u.ravel(), v.ravel()], 1), np.where(finite, truth, 1.0).ravel())
    inside = np.all((pts >= box[0]) & (pts <= box[1]), axis=1).reshape(h, w) & finite
    return truth, inside


def run_lane(scene, cfg) -> dict:
    from reference.common.geometry import mvs as gmvs
    from reference.common.geometry import region

    aerial = list(scene.aerial)
    box = region.region_box(list(scene.ground), cfg.margin_m, (cfg.z_min, cfg.z_max))
    stereo = gmvs.MVSConfig(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(gmvs.MVSConfig)})
    t0 = time.perf_counter()
    cloud, depths, stats = gmvs.run_mvs([f.image() for f in aerial], [f.camera() for f in aerial], box, stereo,
                                        device=cfg.device, max_stretch=cfg.max_stretch)
    secs = time.perf_counter() - t0
    rel, ab, n, n_in = [], [], 0, 0
    for f, d in zip(aerial, depths):
        truth, inside = inside_region(f, box)
        e = depth_errors(d, truth, inside)
        rel.append(e["rel"])
        ab.append(e["abs"])
        n += e["n"]
        n_in += e["n_inside"]
    rel, ab = np.concatenate(rel), np.concatenate(ab)
    return {"lane": scene.name, "seconds": secs, "abs_rel_mean": float(rel.mean()) if len(rel) else float("nan"),
            "abs_rel_median": float(np.median(rel)) if len(rel) else float("nan"),
            "within_0.5m": float((ab <= 0.5).mean()) if len(ab) else 0.0,
            "within_2pct": float((rel <= 0.02).mean()) if len(rel) else 0.0,
            "completeness": n / max(n_in, 1), "points": len(cloud), "raw_coverage": stats["raw_coverage"]}


def figure(runs: list[str], out: str, frames: int = 4) -> None:
    """Rows: a few test frames (first lane, spread over its sequences); columns: ground truth, then
    each reproduce output folder's submitted frame (labelled by the folder's method)."""
    from pathlib import Path

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from skyeyes_bench import imagefiles, outputfiles
    from skyeyes_bench.data.layout import open_dataset
    from skyeyes_bench.protocol import current_for_data, load_protocol
    from skyeyes_bench.splits import scored_view

    cfgs = [json.loads((Path(r) / "config.json").read_text()) for r in runs]
    ds = open_dataset(cfgs[0]["dataset"]["root"])
    # the split the runs scored (a figure shows results: test, or val for a run on it)
    split = cfgs[0]["dataset"].get("split", "test")
    ds = scored_view(ds, split, load_protocol(current_for_data(ds.protocol)))
    scene = ds.split("test")[0]
    seqs = list(scene.sequences.values())
    picks = [seqs[i * len(seqs) // frames] for i in range(frames)]
    picks = [seq.frames[len(seq) // 2] for seq in picks]
    cols = ["ground truth"] + [c["method"] for c in cfgs]
    fig, axes = plt.subplots(len(picks), len(cols), figsize=(2 * len(cols), 2 * len(picks)), squeeze=False)
    for i, f in enumerate(picks):
        imgs = [f.image()] + [imagefiles.read_image(Path(r) / "submission" / scene.name / f.file) for r in runs]
        for j, img in enumerate(imgs):
            ax = axes[i, j]
            ax.imshow(img)
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(cols[j], fontsize=9)
        axes[i, 0].set_ylabel(f.file.rsplit("/", 1)[-1].split(".")[0], fontsize=7)
    fig.tight_layout()
    with outputfiles.atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=80)
    print(f"wrote {out}")


def main(argv=None) -> None:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["figure"]:
        fp = argparse.ArgumentParser(prog="bench/mvs.py figure")
        fp.add_argument("--runs", nargs="+", required=True, help="reproduce output folders")
        fp.add_argument("--out", required=True)
        fp.add_argument("--frames", type=int, default=4)
        a = fp.parse_args(argv[1:])
        figure(a.runs, a.out, a.frames)
        return
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", nargs="+", default=["smoke", "small"])
    screen.split_options(ap, "dataset folder (one preset; default: each preset's SynthTown validation data, "
                         "made if absent)")
    ap.add_argument("--lanes", type=int, default=0, help="validation lanes per preset (0: all)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", default=None, metavar="FILE")
    args = ap.parse_args(argv)
    screening_split(args.split, "bench/mvs.py")  # before anything is imported, made or read
    if args.data is not None and len(args.presets) != 1:
        raise UserError(f"--data {args.data}: with one preset only (--presets {' '.join(args.presets)})")
    from reference.methods.mvs import MVS

    configs = {preset: MVS.configure(preset, args.overrides)[0] for preset in args.presets}  # checked before work
    datasets = {preset: screen.screen_data(args.split, "bench/mvs.py", data=args.data, preset=preset)
                for preset in args.presets}

    import torch

    torch.set_num_threads(args.threads)
    rows = []
    print(f"load average {os.getloadavg()[0]:.2f} at start; torch threads {args.threads}")
    print("| preset | lane | seconds | abs rel mean | abs rel median | within 0.5 m | within 2% | completeness | points |")
    print("|---|---|---|---|---|---|---|---|---|")
    for preset in args.presets:
        cfg, ds = configs[preset], datasets[preset]
        lanes = ds.split("test")[: args.lanes or None]  # the validation lanes (`screen_data`)
        for scene in lanes:
            r = run_lane(scene, cfg)
            r["preset"] = preset
            rows.append(r)
            print(f"| {preset} | {r['lane']} | {r['seconds']:.1f} | {r['abs_rel_mean']:.3f} | {r['abs_rel_median']:.3f} "
                  f"| {r['within_0.5m']:.2f} | {r['within_2pct']:.2f} | {r['completeness']:.2f} | {r['points']} |",
                  flush=True)
    print(f"load average {os.getloadavg()[0]:.2f} at end")
    if args.json:
        from skyeyes_bench import outputfiles

        outputfiles.write_json(args.json, rows)


if __name__ == "__main__":
    screen.run_main(main, sys.argv[1:])
