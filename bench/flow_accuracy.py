"""How well each way a method can move frame j - 1 into frame j agrees with the ground truth's
own correspondence (its depth and the poses, the warp metric's `warp_coords`), on the validation
lanes of a dataset with ground depth (`reference.screen`: `--split test` is refused, docs/evaluate.md, "The split").
The carried noise moves each frame's starting noise by the flow between the prior's renders
(`additions.view.flow_coords`), the street from one view by the ground plane under the prior's
Gaussians (`additions.street`); each is only as good as the way it moves by.

    .venv/bin/python bench/flow_accuracy.py --data ~/.cache/skyeyes-bench/data/synthtown-v2-small-val \\
        --priors ~/.cache/skyeyes-bench/reference/priors --prior RUN/work/KEY/method/prior \\
        [--submission RUN/submission] [--scenes 1] [--sequences 3] [--ways dis-medium,prior-ground] [--rigid]

Ways: an optical flow (dis-medium, what `view.flow_coords` uses; dis-fast, dis-ultrafast,
deepflow, tvl1, farneback, pcaflow: OpenCV's) between the prior's renders (--priors: the folder of
its cached renders, `<scene>-<key>.npz`) and, with --submission, between that submission's
frames; `zero` (no motion); and with --prior (a `sugar` run's folder of `scenes/<scene>/model.pt`,
at --preset) the prior's own depth and the poses (`prior-depth`, `view.prior_depth`), or that
depth with the pixels whose ray meets the ground plane under the prior's Gaussians
(`street.prior_ground`) nearer given the plane's depth (`prior-ground`, `ground_filled`);
`aerial-sweep`, a depth from the aerial views alone (`aerial_sweep_depth`, ~5 s a frame; a depth
way's seconds count its warps only). --rigid adds each flow made rigid with the poses
(`rigid_from_flow`).

Prints, per way: the end-point error (pixels) on the pixels both it and the ground truth call
valid (median, mean, share under 1 px), the share of the truth's valid pixels it covers, its
median error in bands of the ground truth's depth (m), and the seconds it took; the machine's
load before and after.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

from reference import screen
from reference.common.diffusion.additions.street import prior_ground
from reference.common.diffusion.additions.view import FLOW_FB_PX, flow_coords, prior_depth
from skyeyes_bench.errors import UserError
from skyeyes_bench.imagefiles import read_image
from skyeyes_bench.metrics.geometry import project, warp_coords

TOL = screen.TOL  # the protocols' depth tolerance of the warp metric
BANDS = [(0, 5), (5, 10), (10, 20), (20, 100), (100, np.inf)]
FLOWS = ("dis-medium", "dis-fast", "dis-ultrafast", "deepflow", "tvl1", "farneback", "pcaflow")


def flow_fn(name: str):
    """(I_j, I_{j-1}) grey uint8 -> flow [H, W, 2] with I_j(x) ~ I_{j-1}(x + flow(x)): the `flow`
    of `view.flow_coords`, which checks it forward and backward."""
    import cv2

    if name.startswith("dis-"):
        preset = {"dis-fast": cv2.DISOPTICAL_FLOW_PRESET_FAST, "dis-medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
                  "dis-ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST}[name]
        f = cv2.DISOpticalFlow_create(preset)
    elif name == "farneback":
        return lambda a, b: cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 4, 9, 5, 5, 1.1, 0)
    else:
        f = {"deepflow": cv2.optflow.createOptFlow_DeepFlow, "tvl1": cv2.optflow.DualTVL1OpticalFlow_create,
             "pcaflow": cv2.optflow.createOptFlow_PCAFlow}[name]()
    return lambda a, b: f.calc(a, b, None)


def moved_by_depth(depth: np.ndarray, cam, src) -> np.ndarray:
    """Where each pixel of `cam` lands in `src` by its planar depth [H, W] (+inf: a direction),
    with no visibility test: uv [H, W, 2]."""
    o, dirs = cam.rays(normalize=False)  # camera z = 1: the ray's t is planar depth
    fin = np.isfinite(depth).ravel()
    p = np.where(fin[:, None], o + dirs * np.where(fin, depth.ravel(), 0.0)[:, None], dirs)
    q, _ = project(p, fin.astype(np.float64), src.c2w[None], src.K[None])
    return q[0].reshape(depth.shape + (2,))


def rigid_from_flow(uv: np.ndarray, ok: np.ndarray, cam_j, cam_i, *, median_px: int = 5,
                    depths: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A flow's target uv [H, W, 2] (frame i seen from frame j) -> the rigid motion nearest it:
    each pixel's depth along its ray is the one (of log-spaced candidates and +inf) whose
    projection into camera i lands nearest the flow's target, the log-depth is median-filtered
    over `median_px` (the pixels the flow failed take their nearest valid neighbour's first), and
    the pixel moves as that depth and the poses say. -> (uv, depth)."""
    from scipy.ndimage import distance_transform_edt, median_filter

    h, w = ok.shape
    cand = np.geomspace(0.5, 2000.0, 160) if depths is None else depths
    o, dirs = cam_j.rays(normalize=False)
    best, err = np.full(h * w, np.inf), np.full(h * w, np.inf)
    tgt = uv.reshape(-1, 2)
    for d in [*cand, np.inf]:
        p, wt = (o + dirs * d, np.ones(h * w)) if np.isfinite(d) else (dirs, np.zeros(h * w))
        q, _ = project(p, wt, cam_i.c2w[None], cam_i.K[None])
        e = np.hypot(*(q[0] - tgt).T)
        closer = e < err  # NaN (behind the camera) never is
        err[closer], best[closer] = e[closer], d
    far = np.log(cand[-1]) + 1.0  # +inf's place on the log scale
    logd = np.where(np.isfinite(best), np.log(best), far).reshape(h, w)
    hole = ~ok | ~np.isfinite(err.reshape(h, w))
    if hole.all():
        return uv, np.full((h, w), np.inf)
    if hole.any():
        _, (iy, ix) = distance_transform_edt(hole, return_indices=True)
        logd = logd[iy, ix]
    if median_px > 1:
        logd = median_filter(logd, size=median_px, mode="nearest")
    depth = np.where(logd < far - 0.5, np.exp(logd), np.inf)
    return moved_by_depth(depth, cam_j, cam_i), depth


def ground_filled(depth: np.ndarray, cam, zg: float) -> np.ndarray:
    """`depth` [H, W] with each pixel whose ray meets the ground plane z = zg nearer than its
    depth (or where it is +inf: nothing of the prior's) given the plane's depth."""
    o, dirs = cam.rays(normalize=False)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (zg - o[:, 2]) / dirs[:, 2]
    t = np.where((dirs[:, 2] < 0) & (t > 0), t, np.inf).reshape(depth.shape)
    return np.minimum(depth, t)


def aerial_sweep_depth(scene, cam, *, depths: np.ndarray = np.geomspace(2.0, 150.0, 48), best: int = 6,
                       median_px: int = 5) -> np.ndarray:
    """A depth for a ground camera from the aerial views alone (a naive virtual-view plane
    sweep): per pixel and candidate depth, the point is projected into every aerial view, and
    the cost is the mean of the `best` smallest absolute deviations (over the views that see it
    in frame) from the views' median colour; the cheapest depth wins, and its log is
    median-filtered over `median_px`. No visibility reasoning: [H, W] planar depth."""
    import torch
    import torch.nn.functional as F
    from scipy.ndimage import median_filter

    views = scene.aerial
    img = torch.tensor(np.stack([a.image() for a in views]), dtype=torch.float32).permute(0, 3, 1, 2)
    c2ws, ks = np.stack([a.camera().c2w for a in views]), np.stack([a.camera().K for a in views])
    aw, ah = views[0].width, views[0].height
    o, dirs = cam.rays(normalize=False)
    costs = []
    for d in depths:
        uv, _ = project(o + dirs * d, np.ones(len(o)), c2ws, ks)  # [V, N, 2]
        seen = np.isfinite(uv).all(-1) & (uv[..., 0] >= 0) & (uv[..., 0] <= aw) & (uv[..., 1] >= 0) & (uv[..., 1] <= ah)
        grid = torch.tensor(np.nan_to_num(uv) / np.array([aw, ah]) * 2 - 1, dtype=torch.float32)[:, None]
        col = F.grid_sample(img, grid, align_corners=False)[:, :, 0]  # [V, 3, N]
        seen_t = torch.as_tensor(seen)
        col = torch.where(seen_t[:, None], col, torch.nan)
        dev = (col - torch.nanmedian(col, 0).values[None]).abs().mean(1)  # [V, N]
        dev = torch.where(seen_t, dev, torch.inf)
        costs.append(torch.topk(dev, min(best, len(views)), dim=0, largest=False).values.mean(0))
    win = depths[torch.stack(costs).argmin(0).numpy()].reshape(cam.height, cam.width)
    return np.exp(median_filter(np.log(win), size=median_px, mode="nearest"))


def parse_args(argv):
    """The screen's options (`screen.screen_parser`) and this benchmark's; -> (args, the ways)."""
    ap = screen.screen_parser(__doc__)
    ap.set_defaults(scenes=1)
    ap.add_argument("--priors", required=True, type=Path, help="folder of the prior's cached renders (<scene>-<key>.npz)")
    ap.add_argument("--prior", type=Path, default=None, help="a sugar run's folder of scenes/<scene>/model.pt, at "
                    "--preset (the prior-depth and prior-ground ways)")
    ap.add_argument("--submission", type=Path, default=None, help="also the flows between this submission's frames")
    ap.add_argument("--ways", default="zero,dis-medium,prior-depth,prior-ground",
                    help=f"comma-separated: zero, {', '.join(FLOWS)}, prior-depth, prior-ground, aerial-sweep")
    ap.add_argument("--fb-px", type=float, default=FLOW_FB_PX)
    ap.add_argument("--rigid", action="store_true", help="also each flow made rigid (`rigid_from_flow`)")
    ap.add_argument("--median-px", type=int, default=5)
    args = ap.parse_args(argv)
    ways = args.ways.split(",")
    if any(w.startswith("prior-") for w in ways) and args.prior is None:
        ap.error("the prior-depth and prior-ground ways need --prior")
    return args, ways


def tally(stats: dict, key: str, uv, ok, gt_uv, gt_ok, depth, seconds: float) -> None:
    """Count way `key`'s target uv [H, W, 2] (valid where `ok`) against the truth's in `stats`: its
    end-point errors and the truth's depths on the pixels both call valid, its cover, its seconds."""
    both = ok & gt_ok
    s = stats.setdefault(key, {"epe": [], "depth": [], "cover": [0, 0], "s": 0.0})
    s["epe"].append(np.hypot(*(uv[both] - gt_uv[both]).T))
    s["depth"].append(depth[both])
    s["cover"][0] += int(both.sum())
    s["cover"][1] += int(gt_ok.sum())
    s["s"] += seconds


def prior_renders(priors: Path, scene):
    """The prior's cached renders of `scene` (the first `<scene>-*.npz` under `priors`)."""
    found = sorted(priors.expanduser().glob(f"{scene.name}-*.npz"))
    if not found:
        raise UserError(f"--priors {priors}: no {scene.name}-*.npz (the prior's cached renders of that "
                        "scene; run `reproduce` of the preset first)")
    return np.load(found[0])


def street_height(prior, scene, where: Path) -> float:
    """The height of the ground plane under the prior's Gaussians of `scene` (fitted: resumed from
    its checkpoint in `where`), `street.prior_ground`."""
    prior.fit_scene(scene)  # resumed from its checkpoint
    means = prior.scene_model(scene)[0].means.detach().cpu().numpy()
    zg = prior_ground(means, [f.camera().c2w[2, 3] for f in scene.ground])
    if zg is None:
        raise UserError(f"--prior {where}: none of its Gaussians of {scene.name} lie under the ground "
                        "cameras (no street for the prior-ground way)")
    return zg


def score_sequence(args, ways: list[str], stats: dict, scene, q, npz, prior, zg) -> None:
    """Each way's motion from frame j - 1 to frame j of sequence `q` of `scene`, against the
    ground truth's, counted in `stats` (`tally`)."""
    fs = list(q.frames)
    guides = {"prior": np.stack([npz[f.file].astype(np.float32) / 255 for f in fs])}
    if args.submission:
        guides["frames"] = np.stack([read_image(args.submission / scene.name / f.file) for f in fs])
    flows = {(way, g): flow_coords(imgs, fb_px=args.fb_px, flow=flow_fn(way))
             for way in ways if way in FLOWS for g, imgs in guides.items()}
    depths = {}
    if "aerial-sweep" in ways:
        depths["aerial-sweep"] = [aerial_sweep_depth(scene, f.camera()) for f in fs]
    if prior is not None:
        h, w = fs[0].height, fs[0].width
        depths["prior-depth"] = [prior_depth(prior, scene, f, w, h) for f in fs]
        depths["prior-ground"] = [ground_filled(d, f.camera(), zg) for d, f in zip(depths["prior-depth"], fs)]
    for k in range(1, len(fs)):
        a, b = fs[k - 1], fs[k]
        gt_uv, gt_ok = warp_coords(b.depth(), b.camera(), a.depth(), a.camera(), TOL)
        depth = b.depth()
        xs, ys = np.meshgrid(np.arange(b.width) + 0.5, np.arange(b.height) + 0.5)
        for way in ways:
            if way in depths:
                t0 = time.perf_counter()
                uv = moved_by_depth(depths[way][k], b.camera(), a.camera())
                tally(stats, way, uv, np.isfinite(uv).all(-1), gt_uv, gt_ok, depth, time.perf_counter() - t0)
                continue
            for g in guides:
                t0 = time.perf_counter()
                if way == "zero":
                    uv, ok = np.stack([xs, ys], -1), np.ones_like(gt_ok)
                else:
                    uv, ok = flows[way, g](k)
                tally(stats, f"{way} on {g}", uv, ok, gt_uv, gt_ok, depth, time.perf_counter() - t0)
                if args.rigid and way != "zero":
                    t0 = time.perf_counter()
                    ruv, _ = rigid_from_flow(uv, ok, b.camera(), a.camera(), median_px=args.median_px)
                    tally(stats, f"{way} on {g}, rigid", ruv, ok, gt_uv, gt_ok, depth, time.perf_counter() - t0)


def report(stats: dict) -> None:
    """One line per way: its end-point errors, cover, median error by the truth's depth, seconds."""
    for key, s in stats.items():
        e, d = np.concatenate(s["epe"]), np.concatenate(s["depth"])
        bands = [f"{lo}-{hi if np.isfinite(hi) else ''} m {np.median(e[(d >= lo) & (d < hi)]):.2f}"
                 if ((d >= lo) & (d < hi)).any() else f"{lo}- m n/a" for lo, hi in BANDS]
        sky = np.isposinf(d)
        bands.append(f"sky {np.median(e[sky]):.2f}" if sky.any() else "sky n/a")
        print(f"{key:28s} EPE median {np.median(e):.2f} mean {e.mean():.2f} <1px {np.mean(e < 1):.3f} covers "
              f"{s['cover'][0] / s['cover'][1]:.3f}; median by depth: {', '.join(bands)}; {s['s']:.1f} s")


def main(argv=None) -> None:
    args, ways = parse_args(argv)
    _, scenes, seqs = screen.screened(args, "bench/flow_accuracy.py")
    prior = None
    if args.prior is not None:
        from reference.methods.sugar import SuGaR

        prior = SuGaR.from_preset(args.preset, args.prior.expanduser(), progress=False)
    stats: dict[str, dict] = {}
    print(f"load average {os.getloadavg()[0]:.1f}", flush=True)
    for scene in scenes:
        npz = prior_renders(args.priors, scene)
        zg = street_height(prior, scene, args.prior) if prior is not None else None
        mine = [q for s, q in seqs if s is scene]
        for q in mine:
            score_sequence(args, ways, stats, scene, q, npz, prior, zg)
        print(f"{scene.name}: {len(mine)} sequences", flush=True)
    report(stats)
    print(f"load average after {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    screen.run_main(main, sys.argv[1:])
