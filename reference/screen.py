"""What every script that screens settings shares (bench/additions.py, bench/vcm_screen.py, and
the method benches): the data it runs on, which is the validation split and never test
(`screening_split`; docs/evaluate.md, "The split"), and how a setting's frames are scored against their truth.

```
ap = screen_parser(__doc__)            # --data, --split (val), --preset, --scenes, --sequences, --workdir
args = ap.parse_args()
ds, scenes, seqs = screened(args, "bench/x.py")   # a UserError (exit 2, one line) for --split test
ds = screen_data(args.split, "bench/x.py", data=args.data, preset="small")   # the same, options of its own
run_main(main, sys.argv[1:])           # a UserError as one line on stderr, exit 2
```

The scores here are for choosing between settings on the same frames: the warp error, PSNR and
LPIPS as the protocols compute them, and an Inception FID over the screened frames (comparable
between settings of one screen, not with a protocol's FID over all its frames). A setting the
screen picks is then run by `reproduce` and scored by `evaluate` and `compare`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from skyeyes_bench.errors import UserError

#: The protocols' depth tolerance of the warp metric.
TOL = 0.01


def split_options(ap, data_help: str = "dataset folder (default: the SynthTown validation data of --preset, "
                  "made if absent)") -> None:
    """The two options every screen takes, for `screen_data`: --data (a dataset folder) and --split
    (val; test is refused there)."""
    ap.add_argument("--data", type=Path, help=data_help)
    ap.add_argument("--split", default="val", help="the split screened: val (test is refused: settings are chosen on "
                    "validation data, docs/evaluate.md, 'The split')")


def screen_parser(doc: str) -> argparse.ArgumentParser:
    """The options of a screen: the dataset (default: `--preset`'s validation data, made if absent),
    the split (val; test is refused), which scenes and sequences, a work folder."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    split_options(ap, "dataset folder (default: the SynthTown validation data of --preset, made if absent: "
                  "`skyeyes-bench data synthtown --preset P --split val`)")
    ap.add_argument("--preset", default="small", help="the method's preset (default small)")
    ap.add_argument("--scenes", type=int, default=0, help="the first N scenes of the split (0: all)")
    ap.add_argument("--skip", type=int, default=0, help="start at this scene of the split")
    ap.add_argument("--sequences", type=int, default=0, help="the first N sequences of each scene (0: all)")
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/skyeyes-screen"),
                    help="where the screen's methods keep their work (their stages come from the stage cache)")
    return ap


def screen_data(split: str, what: str, *, data=None, preset: str = "small"):
    """The dataset a screen (`what`, e.g. "bench/mvs.py") runs on, as a run on `split` sees it:
    `split` must be val (`splits.screening_split`: test is a one-line UserError, before any data is
    made or read); `data` (default: SynthTown's validation data of `preset`, made if absent) seen
    through `splits.scored_view`, so its "test" scenes are the validation scenes and its "train"
    what a run on them fits."""
    from skyeyes_bench.data.layout import open_dataset
    from skyeyes_bench.protocol import current_for_data, load_protocol
    from skyeyes_bench.splits import scored_view, screening_split

    split = screening_split(split, what)
    if data is None:
        from skyeyes_bench.data.synthtown import ensure_dataset

        data = ensure_dataset(preset, split=split)
    ds = open_dataset(Path(data).expanduser())
    return scored_view(ds, split, load_protocol(current_for_data(ds.protocol)))


def screened(args, what: str):
    """(the dataset as a run on the screened split sees it, its scenes to screen, [(scene, sequence)]):
    `--split` must be val (`splits.screening_split`); the validation scenes are the view's "test"
    (`splits.scored_view`). `screen_data` with the options of `screen_parser`."""
    from skyeyes_bench.splits import screening_split

    screening_split(args.split, what)
    if args.data is None:
        from skyeyes_bench.data.synthtown import ensure_dataset

        args.data = ensure_dataset(args.preset, split=args.split)
    ds = screen_data(args.split, what, data=args.data, preset=args.preset)
    scenes = ds.split("test")[args.skip: args.skip + args.scenes if args.scenes else None]
    seqs = [(s, q) for s in scenes for q in list(s.sequences.values())[: args.sequences or None]]
    return ds, scenes, seqs


def run_main(main, argv=None) -> None:
    """`main(argv)` with a user error as one line on stderr and exit 2 (the CLI's convention)."""
    try:
        main(argv)
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None


def features(images: np.ndarray) -> np.ndarray:
    """FID's features [N, 2048] of frames [N, H, W, 3] in [0, 1] (the protocols' Inception extractor)."""
    from skyeyes_bench.metrics.extractors import get_extractor

    return get_extractor("inception-tf-2015").features(images)


def clip_features(frames: np.ndarray, length: int = 16) -> np.ndarray:
    """FVD's features [K, 400] of a sequence's frames [N, H, W, 3]: its non-overlapping clips of
    `length` frames (the protocols' I3D extractor and clip stride)."""
    from skyeyes_bench.metrics.extractors import get_extractor

    clips = np.stack([frames[s:s + length] for s in range(0, len(frames) - length + 1, length)])
    return get_extractor("i3d-kinetics400").features(clips)


def fid(a: np.ndarray, b: np.ndarray) -> float:
    """The Fréchet distance of two feature sets [N, D]."""
    from skyeyes_bench.metrics.sets import frechet_distance

    return frechet_distance(a.mean(0), np.cov(a, rowvar=False), b.mean(0), np.cov(b, rowvar=False))


def metric_pairs(frames) -> list:
    """The warp metric's (uv, valid) of each consecutive pair of a sequence's frames (the truth's
    depth and poses, the protocols' tolerance)."""
    from skyeyes_bench.metrics.geometry import warp_coords

    return [warp_coords(b.depth(), b.camera(), a.depth(), a.camera(), TOL) for a, b in zip(frames[:-1], frames[1:])]


def scored(x: np.ndarray, frames, pairs) -> tuple[float, int, float, float]:
    """A sequence's frames x [N, H, W, 3] in [0, 1] against its truth (`frames`, `pairs` their
    `metric_pairs`): (warp error pooled over its pairs, the pixels it pools, mean PSNR, mean LPIPS)."""
    from skyeyes_bench.metrics.geometry import warp_error
    from skyeyes_bench.metrics.image import lpips

    gts = np.stack([f.image() for f in frames])
    e = sum(warp_error(x[k], x[k + 1], uv, ok)[0] * int(ok.sum()) for k, (uv, ok) in enumerate(pairs))
    n = sum(int(ok.sum()) for _, ok in pairs)
    psnr = float(np.mean(-10 * np.log10(((x - gts) ** 2).mean(axis=(1, 2, 3)))))
    return e / n, n, psnr, float(lpips(x, gts).mean())


def report(label: str, r: np.ndarray, base: np.ndarray | None, feats: np.ndarray, gt_feats: np.ndarray) -> str:
    """One line for a setting's `scored` rows r [sequences, 4]: the pooled warp error, PSNR, LPIPS and
    the FID of its frames' features; with `base` (the first setting's rows) the warp error's
    paired difference, base minus r, with a 95% bootstrap over sequences, and LPIPS r minus base."""
    w = r[:, 1] / r[:, 1].sum()
    line = (f"{label}: warp {(r[:, 0] * w).sum():.4f} PSNR {r[:, 2].mean():.2f} LPIPS {r[:, 3].mean():.4f} "
            f"FID (these frames) {fid(feats, gt_feats):.1f}")
    if base is not None:
        d = base[:, 0] - r[:, 0]
        boot = np.random.default_rng(0).integers(0, len(d), (2000, len(d)))
        lo, hi = np.percentile((d[boot] * w[boot]).sum(1) / w[boot].sum(1), [2.5, 97.5])
        line += (f"; warp first minus this {(d * w).sum():+.4f} [{lo:+.4f}, {hi:+.4f}], LPIPS this minus first "
                 f"{(r[:, 3] - base[:, 3]).mean():+.4f}")
    return line
