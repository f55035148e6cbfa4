"""Screen sampling settings of `skyeyes` on a few test sequences before a whole `reproduce`:
the stages come from the stage cache (the ACM, VCM and prior renders a `reproduce` of the preset
left there; where they are missing they are trained first, as `reproduce` would, which at
`small` takes hours here), and each setting's frames are scored on the warp error, PSNR, LPIPS and the FID of
those frames against the same sequences' ground truth (an Inception FID over a few hundred
frames: comparable between settings here, not with the protocol's), the warp error and LPIPS
paired per sequence against the first setting's (docs/skyeyes.md, "The VCM").

    .venv/bin/python bench/vcm_screen.py --data ~/.cache/skyeyes-bench/data/synthtown-v2-small \\
        --scenes 1 "clip_frames=1 vcm_noise=0" "clip_frames=1" "clip_frames=1 vcm_lowpass=3 vcm_lowpass_mix=0.7"

A setting is `--set` overrides separated by spaces, on --preset (default small). --moves says
what the carried noise and the low-pass transfer move frames by:

* flow (default): the method's own, the optical flow between the prior's renders;
* rigid: that flow made rigid with the poses (bench/flow_accuracy.py `rigid_from_flow`);
* ground: the prior's depth with the ground plane under its Gaussians filling it
  (`flow_accuracy.ground_filled`), moved by the poses, visible to --tol;
* fused: that depth where it puts the pixel nearer than `FUSED_NEAR_M` (the near road) or at
  +inf (the sky), the flow elsewhere;
* oracle: the ground truth's own correspondence (its depth and the poses, what the warp metric
  uses): an upper bound of what a better flow could give, never a method;
* oracle-where-flow: the truth's motion on the pixels the flow keeps (its forward-backward
  check), the rest of each frame its own: the flow's accuracy made perfect, its reach not;
* flow-where-oracle: the flow where it keeps a pixel, the truth's motion on the others it
  reaches: the flow's reach made the truth's, its accuracy not.

With --hold-flow, warped sampling (`vcm_warp`) holds by the flow between the prior's renders
instead of the prior's depth (clip_frames=1). The prior's fitted scenes are read from
--workdir's `work/prior/scenes` (link a `reproduce` run's `method/prior/scenes` there) for
`vcm_warp` and --moves ground.
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from reference.common.diffusion import warp
from reference.common.diffusion.pipeline import _guides
from reference.common.priors import frame_key
from reference.methods.skyeyes import Skyeyes
from skyeyes_bench.data.layout import open_dataset
from skyeyes_bench.metrics.geometry import warp_coords, warp_error
from skyeyes_bench.metrics.image import lpips

sys.path.insert(0, str(Path(__file__).parent))
from flow_accuracy import ground_filled, rigid_from_flow  # noqa: E402

TOL = 0.01  # the protocols' depth tolerance of the warp metric
#: --moves fused: the prior's depth (with the ground plane) moves what it puts nearer than this
#: (the near road, where the renders' flow fails: bench/flow_accuracy.py) and the sky.
FUSED_NEAR_M = 5.0


def features(net, images: np.ndarray) -> np.ndarray:
    """Inception pool3 features [N, 2048] of frames [N, H, W, 3] in [0, 1] (FID's)."""
    from skyeyes_bench.metrics.inception import preprocess

    with torch.no_grad():
        return np.concatenate([net(preprocess(images[i:i + 32])).double().numpy() for i in range(0, len(images), 32)])


def fid(a: np.ndarray, b: np.ndarray) -> float:
    from skyeyes_bench.metrics.sets import frechet_distance

    return frechet_distance(a.mean(0), np.cov(a, rowvar=False), b.mean(0), np.cov(b, rowvar=False))


def metric_pairs(frames) -> list:
    """The warp metric's (uv, valid) of each consecutive pair of a sequence's frames (the truth's
    depth and poses, the protocols' tolerance)."""
    return [warp_coords(b.depth(), b.camera(), a.depth(), a.camera(), TOL) for a, b in zip(frames[:-1], frames[1:])]


def scored(x: np.ndarray, frames, pairs) -> tuple[float, int, float, float]:
    """A sequence's frames x [N, H, W, 3] in [0, 1] against its truth (`frames`, `pairs` their
    `metric_pairs`): (warp error pooled over its pairs, the pixels it pools, mean PSNR, mean LPIPS)."""
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


def oracle_coords(frames, h: int, w: int):
    """j -> (uv, valid) of frame j - 1 seen from frame j at h x w, by the ground truth's depth
    (on a grid coarser than the frames, `warp.grid_coords` of it)."""
    def coords(j: int):
        a, b = frames[j - 1], frames[j]
        uv, ok = warp_coords(b.depth(), b.camera(), a.depth(), a.camera(), TOL)
        return np.nan_to_num(uv), ok

    return warp.grid_coords(coords, frames[0].height // h)


class FlowTargets(warp.WarpTargets):
    """`warp.WarpTargets` moving the previous frame by `flow` (j -> frame j - 1 seen from j)
    instead of the prior's depth: frame by frame only (clip_frames=1)."""

    def __init__(self, conds: torch.Tensor, flow, cfg):
        self.conds, self.flow, self.cfg = conds, flow, cfg

    def coords(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
        if j != i + 1:
            raise ValueError("--hold-flow holds frame by frame (clip_frames=1)")
        uv, valid = self.flow(j)
        return np.nan_to_num(uv), valid


def moves(kind: str, m: Skyeyes, current: dict, tol: float):
    """A stand-in for `warp.flow_coords(guides)` that moves the current sequence by `kind`."""
    real = warp.flow_coords

    def coords(guides, *, fb_px=warp.FLOW_FB_PX):
        h, w = guides.shape[1:3]
        frames, scene = current["frames"], current["scene"]
        cams = [warp.scaled_camera(f.camera(), w, h) for f in frames]
        if kind == "oracle":
            return oracle_coords(frames, h, w)
        flow = real(guides, fb_px=fb_px)
        if kind in ("oracle-where-flow", "flow-where-oracle"):  # the truth's where... : where the error comes from
            truth = oracle_coords(frames, h, w)

            def split(j: int):
                (tuv, tok), (fuv, fok) = truth(j), flow(j)
                if kind == "oracle-where-flow":  # the truth's motion, on the pixels the flow keeps
                    return tuv, tok & fok
                return np.where(fok[..., None], np.nan_to_num(fuv), tuv), tok  # the flow's, the truth's reach

            return split
        if kind in ("ground", "fused"):
            zg = warp.prior_ground(m.prior, scene)
            depths = [ground_filled(warp.prior_depth(m.prior, scene, f, w, h), c, zg) for f, c in zip(frames, cams)]
            by_depth = warp.depth_coords(depths, cams, tol=tol)

            def depth_or_flow(j: int):
                uv, ok = by_depth(j)
                if kind == "fused":  # the depth where it is the ground plane near by or the sky, else the flow
                    by_flow, flow_ok = flow(j)
                    mine = (depths[j] < FUSED_NEAR_M) | np.isposinf(depths[j])
                    uv, ok = np.where(mine[..., None], uv, by_flow), np.where(mine, ok, flow_ok)
                return np.nan_to_num(uv), ok

            return depth_or_flow

        def rigid(j: int):
            uv, ok = flow(j)
            ruv, _ = rigid_from_flow(uv, ok, cams[j], cams[j - 1], median_px=max(3, w // 16 | 1))
            inside = (ruv[..., 0] >= 0) & (ruv[..., 0] <= w) & (ruv[..., 1] >= 0) & (ruv[..., 1] <= h)
            return np.nan_to_num(ruv), ok & inside

        return rigid

    return coords


def screen_parser(doc: str) -> argparse.ArgumentParser:
    """The options every screen of the stage cache takes: the dataset, the preset, which test
    scenes and sequences, the work folder (`screened`)."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, type=Path)
    ap.add_argument("--preset", default="small")
    ap.add_argument("--scenes", type=int, default=1)
    ap.add_argument("--skip", type=int, default=0, help="start at this test scene")
    ap.add_argument("--sequences", type=int, default=0, help="the first N sequences of each scene (0: all)")
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/vcm-screen"))
    return ap


def screened(args):
    """(dataset, test scenes, [(scene, sequence)]) that `screen_parser`'s options choose."""
    ds = open_dataset(args.data.expanduser())
    scenes = ds.split("test")[args.skip: args.skip + args.scenes]
    seqs = [(s, q) for s in scenes for q in list(s.sequences.values())[: args.sequences or None]]
    return ds, scenes, seqs


def main(argv=None) -> None:
    ap = screen_parser(__doc__)
    ap.add_argument("--moves", choices=("flow", "rigid", "ground", "fused", "oracle", "oracle-where-flow",
                                                    "flow-where-oracle"), default="flow",
                    help="what carried noise and the low-pass transfer move frames by (above)")
    ap.add_argument("--tol", type=float, default=warp.DEPTH_TOL, help="--moves ground: the depth test's tolerance")
    ap.add_argument("--fb-px", type=float, default=warp.FLOW_FB_PX,
                    help="--moves flow: the flow's forward-backward check (`warp.FLOW_FB_PX`)")
    ap.add_argument("--hold-flow", action="store_true", help="`vcm_warp` holds by the prior's renders' flow")
    ap.add_argument("settings", nargs="+", help='each a setting: `--set` overrides separated by spaces, e.g. '
                    '"clip_frames=1 vcm_noise=0"; the first is the one the others are paired against')
    args = ap.parse_args(argv)
    from skyeyes_bench import paths
    from skyeyes_bench.metrics.inception import load_inception

    ds, scenes, seqs = screened(args)
    print(f"{len(seqs)} sequences; load average {os.getloadavg()[0]:.1f}", flush=True)
    pairs = {q.id: metric_pairs(list(q.frames)) for _, q in seqs}
    net = load_inception(paths.cache_dir() / "weights" / "inception-2015-12-05-fid-helper-default_1.pt")
    gt_feats = features(net, np.concatenate([np.stack([f.image() for f in q.frames]) for _, q in seqs]))
    rows = {}
    for setting in args.settings:
        config, _ = Skyeyes.configure(args.preset, setting.split())
        m = Skyeyes(config, args.workdir / "work", progress=False)
        m.fit_train(ds)
        m.fit_scenes(scenes, progress=False)
        current: dict = {}
        if args.moves in ("ground", "fused") or config.vcm_warp:
            for s in scenes:
                m.prior.fit_scene(s)  # resumed from its checkpoint
        if args.hold_flow:
            def targets(scene, sequence, cc, m=m):
                res = m.config.core.resolution
                priors = [m.scene_model(scene)[frame_key(scene, f)] for f in sequence.frames]
                guides = _guides(priors, res, res)
                return FlowTargets(cc, functools.cache(warp.flow_coords(guides)), m.config.core)

            m._warp_targets = targets
        real = warp.flow_coords
        if args.moves != "flow":
            warp.flow_coords = moves(args.moves, m, current, args.tol)
        elif args.fb_px != warp.FLOW_FB_PX:
            warp.flow_coords = functools.partial(real, fb_px=args.fb_px)
        t0 = time.perf_counter()
        per, frames_out = [], []
        try:
            for s, q in seqs:
                frames = list(q.frames)
                current.update(frames=frames, scene=s)
                x = np.stack(list(m.render_sequence(s, q)))
                per.append(scored(x, frames, pairs[q.id]))
                frames_out.append(x)
        finally:
            warp.flow_coords = real
        dt = time.perf_counter() - t0
        rows[setting] = np.array(per)
        label = f"[{setting}] moves {args.moves}{', hold by flow' if args.hold_flow else ''}"
        print(report(label, rows[setting], rows[args.settings[0]] if len(rows) > 1 else None,
                     features(net, np.concatenate(frames_out)), gt_feats) + f"; render {dt:.0f} s", flush=True)
    print(f"load average after {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
