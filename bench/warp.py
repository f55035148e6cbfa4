"""The warp error of validation-split submissions on any dataset with ground depth, paired against
the first one: the research loop of the view consistency module at `smoke`, whose protocol
(synthtown@1) has no warp metric (docs/skyeyes.md, "What was tried"). Settings are compared here,
so the runs are on the validation split (`reproduce --split val`), never on test (docs/evaluate.md, "The split"):
a submission whose submission.json says split "test" exits 2.

    .venv/bin/python bench/warp.py RUN [RUN ...]
    .venv/bin/python bench/warp.py --data ~/.cache/skyeyes-bench/data/synthtown-smoke-val RUN [RUN ...]

RUN is a `reproduce --split val --out` folder (its `submission/`) or a submission folder; every
RUN holds the same dataset's validation frames. --data: that dataset's folder (default: where
`evaluate` finds it, `<cache>/data/<dataset name>`), seen as a run on its validation split sees
it. Prints, per run, the warp error (frame t warped into frame t + 1 with the ground truth's depth
and poses, mean absolute difference over the valid pixels, pooled over every pair as the
protocols pool it; depth tolerance 0.01) and the ground truth's own floor; for every run after
the first, the paired difference over sequences (first minus run: > 0 means the run flickers
less) with a 95% bootstrap interval over sequences, and the sequences where it is lower.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from reference import screen
from skyeyes_bench import imagefiles
from skyeyes_bench.errors import UserError
from skyeyes_bench.metrics.geometry import warp_coords, warp_error

TOL = screen.TOL


def submission_dir(run: Path) -> Path:
    return run / "submission" if (run / "submission").is_dir() else run


def validation_data(runs: list[Path], data=None):
    """The dataset the runs' submissions were made for, as a run on the validation split sees it;
    a one-line UserError for a submission on the test split or of another dataset than the first."""
    from skyeyes_bench.evaluate import open_inputs
    from skyeyes_bench.submission import SUBMISSION_FILE, read_submission

    names = []
    for run in runs:
        sub = submission_dir(run)
        m = read_submission(sub)
        split = m["dataset"].get("split", "test")
        if split != "val":
            raise UserError(f"{sub / SUBMISSION_FILE}: field 'dataset.split' is {split!r}: bench/warp.py compares "
                            "settings, so it takes submissions on the validation split only (`skyeyes-bench "
                            "reproduce --split val`)")
        names.append(m["dataset"]["name"])
    if len(set(names)) > 1:
        raise UserError(f"{submission_dir(runs[0]) / SUBMISSION_FILE}: the runs hold frames of different datasets "
                        f"({', '.join(sorted(set(names)))}); expected one")
    _, _, ds = open_inputs(submission_dir(runs[0]), data, split="val")
    return ds


def sequence_errors(ds, runs: list[Path]) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(sequence ids, [R + 1, S] pooled warp error per sequence: the ground truth then each run,
    [S] valid pixel counts) over the "test" scenes of `ds` (`validation_data`: the validation scenes)."""
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


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=None, help="dataset folder (with ground depth; default: where evaluate finds "
                    "the runs' dataset)")
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    ds = validation_data(args.runs, Path(args.data).expanduser() if args.data else None)
    ids, e, n = sequence_errors(ds, args.runs)
    pooled = (e * n).sum(axis=1) / n.sum()
    print(f"{len(ids)} sequences of {ds.name}'s {ds.scored} split; ground-truth floor {pooled[0]:.4f}")
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
    screen.run_main(main, sys.argv[1:])
