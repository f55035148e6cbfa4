"""The warp error of submissions on any dataset with ground depth, paired against the first one:
the research loop of the view consistency module at `smoke`, whose protocol (synthtown@1) has no
warp metric (docs/skyeyes.md, "What was tried").

    .venv/bin/python bench/warp.py --data ~/.cache/skyeyes-bench/data/synthtown-smoke RUN [RUN ...]

RUN is a `reproduce --out` folder (its `submission/`) or a submission folder. Prints, per run, the
warp error (frame t warped into frame t + 1 with the ground truth's depth and poses, mean absolute
difference over the valid pixels, pooled over every pair as the protocols pool it; depth
tolerance 0.01) and the ground truth's own floor; for every run after the first, the paired
difference over sequences (first minus run: > 0 means the run flickers less) with a 95% bootstrap
interval over sequences, and the sequences where it is lower.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from skyeyes_bench import imagefiles
from skyeyes_bench.data.layout import open_dataset
from skyeyes_bench.metrics.geometry import warp_coords, warp_error

TOL = 0.01


def submission_dir(run: Path) -> Path:
    return run / "submission" if (run / "submission").is_dir() else run


def sequence_errors(data: Path, runs: list[Path]) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(sequence ids, [R + 1, S] pooled warp error per sequence: the ground truth then each run,
    [S] valid pixel counts)."""
    ds = open_dataset(data)
    ids, errs, counts = [], [], []
    for scene in ds.split("test"):
        for q in scene.sequences.values():
            fs = list(q.frames)
            sums, n = np.zeros(len(runs) + 1), 0
            for a, b in zip(fs[:-1], fs[1:]):
                uv, valid = warp_coords(b.depth(), b.camera(), a.depth(), a.camera(), TOL)
                pairs = [(a.image(), b.image())] + [
                    tuple(imagefiles.read_image(submission_dir(r) / scene.name / f.file) for f in (a, b)) for r in runs]
                for k, (x, y) in enumerate(pairs):
                    e, m = warp_error(x, y, uv, valid)
                    sums[k] += e * m if m else 0.0
                n += int(valid.sum())
            ids.append(f"{scene.name}/{q.name}")
            errs.append(sums / max(n, 1))
            counts.append(n)
    return ids, np.array(errs).T, np.array(counts, float)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="dataset folder (with ground depth)")
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    ids, e, n = sequence_errors(Path(args.data).expanduser(), args.runs)
    pooled = (e * n).sum(axis=1) / n.sum()
    print(f"{len(ids)} sequences; ground-truth floor {pooled[0]:.4f}")
    rng = np.random.default_rng(args.seed)
    boot = rng.integers(0, len(ids), (2000, len(ids)))
    for k, run in enumerate(args.runs, start=1):
        line = f"{run}: warp {pooled[k]:.4f}"
        if k > 1:
            d = e[1] - e[k]  # > 0: this run flickers less than the first
            w = n / n.sum()
            reps = (d[boot] * w[boot]).sum(axis=1) / w[boot].sum(axis=1)
            lo, hi = np.percentile(reps, [2.5, 97.5])
            line += (f"; first minus this {(d * w).sum():+.4f} [{lo:+.4f}, {hi:+.4f}]; lower in "
                     f"{int((d > 0).sum())} of {len(ids)} sequences")
        print(line)


if __name__ == "__main__":
    main()
