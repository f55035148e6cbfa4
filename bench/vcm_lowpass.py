"""The low-pass transfer (`vcm_lowpass`) screened offline: applied to a frame-by-frame
submission's frames (the ACM's, which the transfer starts from), with a Gaussian prior's fitted
scenes for the depth, on the first scenes of a dataset with ground depth. Each setting costs
seconds, so a sweep runs before a whole `reproduce` (docs/skyeyes.md, "The VCM").

    .venv/bin/python bench/vcm_lowpass.py --data ~/.cache/skyeyes-bench/data/synthtown-v2-small \\
        --submission RUN/submission --prior RUN/work/KEY/method/prior --scenes 2 2:1 3:1 2:0.7

With --write DIR (one setting) it writes the frames of every test scene, transferred, as a
submission to score with `skyeyes-bench evaluate DIR` and pair against the original with
`compare` (the frames before the transfer are the original's, so the difference is the
transfer's alone).

With --bands SIGMA it prints where the flicker is instead: the warp error of the submission's
and the ground truth's frames low-passed with a Gaussian of SIGMA px, and of what is left, each
also split by the truth's depth of the later frame's pixel (`DEPTH_BANDS`; its +inf: the sky).

A setting is SIGMA:MIX (`vcm_lowpass`, `vcm_lowpass_mix`). --prior is the folder of a `sugar`
run's scene checkpoints (`scenes/<scene>/model.pt`, e.g. a Skyeyes run's `method/prior` with
`vcm_warp` or `vcm_lowpass` on; its preset and seed by --prior-preset, --seed). Prints, per
setting and for the frames untouched: the warp error (the ground truth's depth and poses,
pooled as the protocols pool it, tolerance 0.01), PSNR, LPIPS (AlexNet) and the detail kept
(mean absolute image gradient over the ground truth's); for each setting the untouched frames'
warp error minus its own (> 0: it flickers less) with a 95% bootstrap interval over sequences.
"""

from __future__ import annotations

import argparse
import functools
from pathlib import Path

import numpy as np
import torch

from reference.common.diffusion import warp
from reference.methods.sugar import SuGaR
from skyeyes_bench.data.layout import open_dataset
from skyeyes_bench.imagefiles import read_image
from skyeyes_bench.metrics.geometry import sample_bilinear, warp_coords, warp_error
from skyeyes_bench.metrics.image import lpips

TOL = 0.01  # the protocols' depth tolerance of the warp metric
#: --bands: the bands of the truth's depth (m) the warp error is split by; past the last, the sky.
DEPTH_BANDS = np.array([0.0, 5.0, 10.0, 20.0, 100.0, np.inf])


def _detail(x: np.ndarray) -> float:
    return float(np.abs(np.diff(x, axis=0)).mean() + np.abs(np.diff(x, axis=1)).mean())


def filled_depth(depth: np.ndarray) -> np.ndarray:
    """`depth` [H, W] with every +inf pixel (nothing of the prior's there) given the depth of its
    nearest finite pixel (`scipy.ndimage.distance_transform_edt`); all +inf stays all +inf."""
    from scipy.ndimage import distance_transform_edt

    hole = ~np.isfinite(depth)
    if not hole.any() or hole.all():
        return depth.copy()
    _, (iy, ix) = distance_transform_edt(hole, return_indices=True)
    return depth[iy, ix]


def _depths(frames, scene, prior, res: int, source: str) -> list[np.ndarray]:
    """The depth the transfer warps by: the prior's (what a method has), or for comparison the
    ground truth's (the metric's own: an upper bound) or none (+inf: a direction, so a camera
    that only moves forward warps each pixel to itself)."""
    if source in ("prior", "filled"):
        depths = [warp.prior_depth(prior, scene, f, res, res) for f in frames]
        return depths if source == "prior" else [filled_depth(d) for d in depths]
    if source == "gt":
        return [f.depth() for f in frames]
    return [np.full((res, res), np.inf) for _ in frames]


def _coords(seq, scene, prior, raw: np.ndarray, source: str, fb_px: float):
    """The transfer's j -> (uv, valid) for `seq` by `source` (--depth), each pair computed once:
    flow between the prior's renders (the conditions) or the frames themselves, or a depth."""
    frames = list(seq.frames)
    if source.startswith("flow"):
        guides = np.stack(list(prior.render_sequence(scene, seq))) if source == "flow-prior" else raw
        coords = warp.flow_coords(guides, fb_px=fb_px)
    else:
        res = frames[0].height
        coords = warp.depth_coords(_depths(frames, scene, prior, res, source),
                                   [warp.scaled_camera(f.camera(), res, res) for f in frames])
    return functools.cache(coords)


def _transfer(raw: np.ndarray, coords, setting) -> np.ndarray:
    """Frames [N, H, W, 3] -> the same, transferred with `setting` (SIGMA, MIX)."""
    out = warp.lowpass_transfer(torch.from_numpy(raw).permute(0, 3, 1, 2), coords, *setting)
    return out.permute(0, 2, 3, 1).numpy()


def submission_frames(sub: Path, scene, frames) -> np.ndarray:
    """A submission's frames of `scene` [N, H, W, 3] in [0, 1], in the order of `frames`."""
    return np.stack([read_image(sub / scene.name / f.file) for f in frames])


def _sequence(seq, sub: Path, scene, prior, settings, source: str, fb_px: float) -> dict:
    """Per setting (None: untouched): (warp error sum, valid pixels, PSNR list, LPIPS list, detail, gt detail)."""
    frames = list(seq.frames)
    raw = submission_frames(sub, scene, frames)
    gts = np.stack([f.image() for f in frames])
    coords = _coords(seq, scene, prior, raw, source, fb_px)
    pairs = [warp_coords(b.depth(), b.camera(), a.depth(), a.camera(), TOL) for a, b in zip(frames[:-1], frames[1:])]
    out = {}
    for s in [None, *settings]:
        x = raw if s is None else _transfer(raw, coords, s)
        e = sum(warp_error(x[k], x[k + 1], uv, valid)[0] * int(valid.sum()) for k, (uv, valid) in enumerate(pairs))
        n = sum(int(valid.sum()) for _, valid in pairs)
        psnr = -10 * np.log10(((x - gts) ** 2).mean(axis=(1, 2, 3)))
        out[s] = (e, n, psnr, lpips(x, gts), sum(map(_detail, x)), sum(map(_detail, gts)))
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, type=Path, help="dataset folder (with ground depth)")
    ap.add_argument("--submission", required=True, type=Path, help="a frame-by-frame run's submission folder")
    ap.add_argument("--prior", required=True, type=Path, help="a sugar run's folder of scenes/<scene>/model.pt")
    ap.add_argument("--prior-preset", default="small")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scenes", type=int, default=2, help="the first N test scenes")
    ap.add_argument("--fb-px", type=float, default=warp.FLOW_FB_PX, help="flow: the forward-backward check's pixels")
    ap.add_argument("--depth", choices=("prior", "filled", "gt", "none", "flow-prior", "flow-frames"), default="prior",
                    help="what the transfer warps by: the prior's depth (default; what the method has), filled "
                         "where it is +inf (`filled_depth`), the "
                         "ground truth's (an upper bound), none (+inf everywhere)")
    ap.add_argument("settings", nargs="+", help="SIGMA:MIX, e.g. 2:1")
    ap.add_argument("--bands", type=float, default=None, metavar="SIGMA",
                    help="print instead where the flicker is: the warp error of the submission's and the ground "
                         "truth's frames low-passed with a Gaussian of SIGMA px, and of the rest")
    ap.add_argument("--write", type=Path, default=None, help="write the transferred frames of every test scene "
                    "(one setting) as a submission here")
    args = ap.parse_args(argv)
    settings = [tuple(float(v) for v in s.split(":")) for s in args.settings]
    ds = open_dataset(args.data.expanduser())
    prior = SuGaR.from_preset(args.prior_preset, args.prior, seed=args.seed, progress=False)
    if args.bands is not None:
        return _bands(ds, args.submission, args.scenes, args.bands)
    if args.write is not None:
        if len(settings) != 1 or not args.depth.startswith("flow"):
            ap.error("--write takes one setting and a flow (--depth flow-prior or flow-frames)")
        return _write(args, ds, prior, settings[0])
    rows = []
    for scene in ds.split("test")[: args.scenes]:
        prior.fit_scene(scene)  # resumed from its checkpoint
        for q in scene.sequences.values():
            rows.append(_sequence(q, args.submission, scene, prior, settings, args.depth, args.fb_px))
    rng = np.random.default_rng(args.seed)
    boot = rng.integers(0, len(rows), (2000, len(rows)))
    n = np.array([r[None][1] for r in rows], float)
    base = np.array([r[None][0] for r in rows]) / n
    print(f"{len(rows)} sequences of {args.scenes} scenes")
    for s in [None, *settings]:
        e = np.array([r[s][0] for r in rows]) / n
        psnr = np.concatenate([r[s][2] for r in rows]).mean()
        lp = np.concatenate([r[s][3] for r in rows]).mean()
        detail = sum(r[s][4] for r in rows) / sum(r[s][5] for r in rows)
        line = (f"{'untouched' if s is None else f'sigma {s[0]:g} mix {s[1]:g}'}: warp {(e * n).sum() / n.sum():.4f} "
                f"PSNR {psnr:.2f} LPIPS {lp:.4f} detail {detail:.3f}")
        if s is not None:
            d = base - e
            reps = (d[boot] * n[boot]).sum(axis=1) / n[boot].sum(axis=1)
            lo, hi = np.percentile(reps, [2.5, 97.5])
            line += f"; untouched minus this {(d * n).sum() / n.sum():+.4f} [{lo:+.4f}, {hi:+.4f}]"
        print(line, flush=True)


def _bands(ds, sub: Path, scenes: int, sigma: float) -> None:
    """The warp error of whole frames, their low-pass and their high-pass, submission and ground truth."""
    from scipy.ndimage import gaussian_filter

    def parts(x):
        low = gaussian_filter(x, (sigma, sigma, 0))
        return x, low, x - low

    sums, n = np.zeros((2, 3)), 0
    by_depth, count = np.zeros((2, 3, len(DEPTH_BANDS))), np.zeros(len(DEPTH_BANDS))
    for scene in ds.split("test")[:scenes]:
        for q in scene.sequences.values():
            fs = list(q.frames)
            for a, b in zip(fs[:-1], fs[1:]):
                uv, valid = warp_coords(b.depth(), b.camera(), a.depth(), a.camera(), TOL)
                n += int(valid.sum())
                band = np.searchsorted(DEPTH_BANDS, b.depth()[valid], side="right") - 1  # the sky (+inf): the last
                count += np.bincount(band, minlength=len(DEPTH_BANDS))
                for r, (x, y) in enumerate([(read_image(sub / scene.name / a.file), read_image(sub / scene.name / b.file)),
                                            (a.image(), b.image())]):
                    for k, (u, v) in enumerate(zip(parts(x), parts(y))):
                        e, m = warp_error(u, v, uv, valid)
                        sums[r, k] += e * m
                        px = np.abs(np.asarray(v, np.float64)[valid] - sample_bilinear(u, uv[valid])).mean(1)
                        by_depth[r, k] += np.bincount(band, weights=px, minlength=len(DEPTH_BANDS))
    names = [f"{lo:g}-{hi:g} m" for lo, hi in zip(DEPTH_BANDS[:-1], DEPTH_BANDS[1:])] + ["sky"]
    print("the truth's depth of the later frame's pixel: " + ", ".join(
        f"{k} {c / max(count.sum(), 1):.3f} of the pixels" for k, c in zip(names, count)))
    for r, (name, row) in enumerate(zip(("submission", "ground truth"), sums / max(n, 1))):
        print(f"{name}: warp {row[0]:.4f}, low-pass (sigma {sigma:g} px) {row[1]:.4f}, the rest {row[2]:.4f}")
        for k, part in enumerate(("warp", "low-pass", "the rest")):
            print(f"  {part} by depth: " + ", ".join(f"{b} {e / max(c, 1):.4f}" for b, e, c in zip(names, by_depth[r, k], count)))


def write_transformed(submission: Path, out: Path, ds, suffix: str, extra: dict, transform) -> None:
    """Every test scene's frames of `submission`, each sequence's [N, H, W, 3] in [0, 1] through
    `transform(scene, sequence, frames)` (the same shape), as a submission in `out`: its method
    named with `suffix`, its config with `extra` (the setting and the command that made it)."""
    import json

    from skyeyes_bench.submission import SubmissionWriter

    meta = json.loads((submission / "submission.json").read_text())
    with SubmissionWriter(out, dataset=ds, method=meta["method"] + suffix, method_version=meta.get("method_version", ""),
                          config={**meta.get("config", {}), **extra}, overwrite=True) as w:
        for scene in ds.split("test"):
            for q in scene.sequences.values():
                frames = list(q.frames)
                raw = submission_frames(submission, scene, frames)
                for f, img in zip(frames, transform(scene, q, raw), strict=True):
                    w.add(scene.name, f, img)
        w.finish(timings={})
    print(f"wrote {out}")


def _write(args, ds, prior, setting) -> None:
    """Every test scene's frames of --submission, transferred with `setting`, as a submission in --write."""
    def transfer(scene, q, raw):
        prior.fit_scene(scene)  # resumed from its checkpoint
        return _transfer(raw, _coords(q, scene, prior, raw, args.depth, args.fb_px), setting)

    extra = {"vcm_lowpass": setting[0], "vcm_lowpass_mix": setting[1],
             "transfer": f"bench/vcm_lowpass.py --depth {args.depth} --fb-px {args.fb_px}"}
    write_transformed(args.submission, args.write, ds, "-lowpass", extra, transfer)


if __name__ == "__main__":
    main()
