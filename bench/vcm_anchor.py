"""The prior's render as the anchor of each frame's coarse part (issue 36), screened on a few test
sequences from the stage cache, as bench/vcm_screen.py screens settings of the sampler.

The 3D prior's renders hardly flicker (warp error 0.018 on SynthTown's first test scene, where
the ground truth's is 0.013 and `skyeyes`' 0.061), so a frame's low frequencies taken from its
render are as steady as the prior; what that costs in realism is what this measures. Every
setting starts from the same frames: the `small` preset's ACM frame by frame (`clip_frames=1`),
from its starting noise (carried along the renders' flow, `vcm_noise_flow`).

    PYTHONPATH= .venv/bin/python bench/vcm_anchor.py --data ~/.cache/skyeyes-bench/data/synthtown-v2-small \\
        --workdir /tmp/vcm-screen after:3:0.7 after:3:0.7:map sampler:3:1:render:0:9

A setting is WHERE:SIGMA:MIX[:TARGET[:FROM:TO]]:

* after:SIGMA:MIX[:render|map|carried]: after sampling, each frame's Gaussian low-pass (std SIGMA
  px) moves MIX of the way towards a target's: `render`, the prior's render's (default); `map`,
  the same with the render's colours first mapped to the frames' by one affine fit a sequence
  (`warp.prior_anchor`, what `vcm_anchor` does: the ACM's colour correction of the
  prior kept); `carried`, the frame's residual
  over its render carried on along the renders' optical flow (`warp.lowpass_transfer` of the
  residual: the render's part of the low-pass stays the frame's own render's).
  `mapN`: the maps on an N x N grid of the screen (`vcm_anchor_tiles`); `mapNwK`: fitted for each
  frame over the K frames either side of it only, so the map follows the street as it changes.
  `lmap...`: the map fitted on the low-passes (std SIGMA) of render and frames, not on their
  pixels; `omap...`: on the low-passes too, matching the colour distributions (means and
  covariances) instead of predicting the frames' colours (`warp.affine_colours`' fit="monge"),
  so the target keeps the frames' contrast where a regression shrinks it.
  after:SIGMA:MIX:mapN:CHROMA moves the low-pass's luma (Rec. 601) by MIX and the rest, its
  chroma, by CHROMA.
* time:SIGMA:TAU: after sampling, the low-pass's residual over the render (colours mapped on a
  4x4 grid) smoothed over time on the screen (a Gaussian of std TAU frames), with no target.
* flow:SIGMA:W:mean|median: after sampling, each frame's detail (what its Gaussian low-pass leaves)
  averaged with its two neighbours' (weight W each) or replaced by the median of the three, the
  neighbours' moved along the renders' optical flow where its forward-backward check holds.
* Settings joined by `+` are applied one after the other (e.g. after:3:0.5:map4+after:6:0.8:map4).
* sampler:SIGMA:MIX:render|map[N]:FROM:TO: inside the sampler, for DDIM steps FROM..TO-1, the low-pass
  of the x0 estimate moves MIX of the way to the target's and the step goes on from it (Iterative
  Latent Variable Refinement, Choi et al. 2021, on the x0 estimate); `map` fits the render's colours
  to the x0 estimate of step FROM, pooled over the sequence's frames (`mapN`: on an N x N grid).

Scored as bench/vcm_screen.py scores (`report`): the warp error against the frames as sampled with
a 95% bootstrap over sequences, PSNR, LPIPS and the FID of these frames against their truth.
--workdir's `work/` holds (or gets) the preset's stage cache, as vcm_screen's does.

With --submission SUB (and no --write), the `after` settings are screened on SUB's frames (a
`small` run's, read as 8-bit PNGs, and each setting's frames rounded to 8 bits as a submission
holds them) instead of frames sampled here: on all 8 test scenes (--scenes 8) the point values
are `evaluate`'s (the warp error, PSNR, LPIPS, FID over the 2048 frames), in about 4 minutes a
setting on this machine where `--write` and `evaluate` take 15; `compare`'s intervals still
need `evaluate`.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from reference.common.diffusion import core, warp
from reference.common.diffusion import sample as S
from reference.common.diffusion.pipeline import _guides, to_model
from reference.common.priors import frame_key
from reference.methods.skyeyes import Skyeyes

sys.path.insert(0, str(Path(__file__).parent))
from vcm_screen import features, metric_pairs, report, scored, screen_parser, screened  # noqa: E402


def sample_anchored(acm, cc: torch.Tensor, noise: torch.Tensor, steps: int, setting) -> torch.Tensor:
    """The frames' model-space samples [N, C, h, w] by deterministic DDIM (`sample.ddim`'s steps),
    the low-pass of the x0 estimate held to the render's (`setting`: sampler) for steps FROM..TO-1."""
    _, sigma, mix, target, k0, k1 = setting
    cfg = acm.cfg
    sched = S._scheduler(cfg, steps)
    ac = sched.alphas_cumprod
    x = noise * sched.init_noise_sigma
    render = F.pixel_shuffle(core._prior(cc, cfg), cfg.patch)  # the residual's prior, an image in [-1, 1]
    goal = None
    for k, t in enumerate(sched.timesteps):
        with torch.no_grad():
            v = acm(x, S._timesteps(t, x.shape[0], x.device), cc).float()
        a = ac[t]
        x0 = (a.sqrt() * x - (1 - a).sqrt() * v).clamp(-sched.config.clip_sample_range, sched.config.clip_sample_range)
        eps = (x - a.sqrt() * x0) / (1 - a).sqrt()  # diffusers' DDIM recomputes it from the clipped x0
        if k0 <= k < k1:
            r = F.pixel_shuffle(x0, cfg.patch) / cfg.residual_scale  # the image's residual over the render
            if goal is None:  # the residual the target asks for
                goal = (warp.affine_colours(render, render + r, int(target[3:] or 1)) if target.startswith("map")
                        else render) - render
            x0 = F.pixel_unshuffle(warp.anchored(r, goal, sigma, mix) * cfg.residual_scale, cfg.patch)
        tp = int(t) - cfg.train_timesteps // steps
        ap = ac[tp] if tp >= 0 else sched.final_alpha_cumprod
        x = ap.sqrt() * x0 + (1 - ap).sqrt() * eps
    return x


#: Rec. 601 luma weights: `after:...:CHROMA` moves the low-pass's luma and chroma apart.
LUMA = torch.tensor([0.299, 0.587, 0.114])


#: A map target's prefix -> how `warp.affine_colours` fits it: on the pixels (the preset's), or on
#: the setting's low-passes, by least squares (l) or by matching the colour distributions (o).
FITS = {"": ("lstsq", False), "l": ("lstsq", True), "o": ("monge", True)}


def mapped(imgs: torch.Tensor, renders: torch.Tensor, target: str, sigma: float = 0.0) -> torch.Tensor:
    """`target` [l|o]mapN[wK]: the renders' colours mapped to the frames' (`warp.affine_colours` on
    an N x N grid, fitted as `FITS` says, on low-passes of std `sigma`), over the whole sequence
    or, with wK, for each frame over the K frames either side."""
    prefix, _, rest = target.partition("map")
    fit, low = FITS[prefix]
    how = {"fit": fit, "sigma": sigma if low else 0.0}
    tiles, _, k = rest.partition("w")
    tiles = int(tiles or 1)
    if not k:
        return warp.affine_colours(renders, imgs, tiles, **how)
    k = int(k)
    return torch.stack([warp.affine_colours(renders[max(0, t - k): t + k + 1], imgs[max(0, t - k): t + k + 1],
                                            tiles, **how)[min(t, k)] for t in range(len(imgs))])


def in_time(imgs: torch.Tensor, renders: torch.Tensor, setting) -> torch.Tensor:
    """Frames [N, 3, H, W] in [0, 1] smoothed over time after sampling (`setting`: time, flow)."""
    from scipy.ndimage import gaussian_filter1d

    x = imgs.double().numpy()
    if setting[0] == "time":
        _, sigma, tau = setting
        d = warp.blur_frames(imgs, sigma) - warp.blur_frames(mapped(imgs, renders, "map4"), sigma)
        return torch.from_numpy(x + gaussian_filter1d(d, tau, axis=0, mode="nearest") - d).clamp(0, 1).to(imgs.dtype)
    _, sigma, w, how = setting
    g = renders.permute(0, 2, 3, 1).numpy()
    back, ahead = warp.flow_coords(g), warp.flow_coords(g[::-1].copy())  # frame j - 1 (j + 1) seen from j
    detail, n = x - warp.blur_frames(imgs, sigma), len(x)
    out = x.copy()
    for j in range(n):
        near = []
        for k, coords, i in ((j - 1, back, j), (j + 1, ahead, n - 1 - j)):
            if 0 <= k < n:
                uv, ok = coords(i)
                near.append((warp.warp_image(torch.from_numpy(detail[k]), uv, ok).numpy(), ok))
        if how == "median":
            if len(near) == 2:
                out[j] += np.median([detail[j], *[np.where(ok[None], d, detail[j]) for d, ok in near]], 0) - detail[j]
        else:
            total, weight = detail[j].copy(), np.ones(x.shape[2:])
            for d, ok in near:
                total, weight = total + w * d, weight + w * ok
            out[j] += total / weight - detail[j]
    return torch.from_numpy(out).clamp(0, 1).to(imgs.dtype)


def after(imgs: torch.Tensor, renders: torch.Tensor, setting) -> torch.Tensor:
    """Frames [N, 3, H, W] in [0, 1] anchored after sampling (`setting`: after, time, flow, or a
    chain of them)."""
    if setting[0] == "chain":
        for s in setting[1:]:
            imgs = after(imgs, renders, s)
        return imgs
    if setting[0] in ("time", "flow"):
        return in_time(imgs, renders, setting)
    _, sigma, mix, target = setting[:4]
    chroma = setting[4] if len(setting) > 4 else mix
    if target == "carried":
        coords = warp.flow_coords(renders.permute(0, 2, 3, 1).numpy())
        moved = warp.lowpass_transfer((imgs - renders) / 2 + 0.5, coords, sigma, mix)
        return (renders + 2 * (moved - 0.5)).clamp(0, 1)
    if target.startswith("map") and "w" not in target and chroma == mix:  # what `vcm_anchor` does
        return warp.prior_anchor(imgs, renders, sigma, mix, int(target[3:] or 1))
    goal = mapped(imgs, renders, target, sigma) if _is_map(target) else renders
    if chroma == mix:
        return warp.anchored(imgs, goal, sigma, mix).clamp(0, 1)
    move = warp.anchored(imgs, goal, sigma, 1.0) - imgs  # the whole way, low-pass only
    luma = (move * LUMA.to(move)[None, :, None, None]).sum(1, keepdim=True)  # a grey shift of that luma
    return (imgs + mix * luma + chroma * (move - luma)).clamp(0, 1)


def _renders(args, ds, scenes):
    """(scene, sequence, h, w) -> the stage cache's conditions of the sequence's frames (the
    prior's renders a `small` run's frames were generated from), [N, 3, h, w] in [0, 1]; with
    --anchor-frames, that submission's frames instead (another 3D method's renders)."""
    if args.anchor_frames is not None:
        from vcm_lowpass import submission_frames

        return lambda scene, q, h, w: torch.from_numpy(
            submission_frames(args.anchor_frames, scene, list(q.frames))).permute(0, 3, 1, 2).float()
    config, _ = Skyeyes.configure(args.preset, args.set)
    m = Skyeyes(config, args.workdir / "work", progress=False)
    m.fit_train(ds)
    m.fit_scenes(scenes, progress=False)

    def of(scene, q, h: int, w: int) -> torch.Tensor:
        priors = [m.scene_model(scene)[frame_key(scene, f)] for f in q.frames]
        return torch.from_numpy(_guides(priors, h, w)).permute(0, 3, 1, 2)

    return of


def _write(args, ds, setting) -> None:
    """--submission's frames of every test scene anchored by `setting` to the stage cache's
    conditions (the prior's renders the submission's frames were generated from), into --write."""
    from vcm_lowpass import write_transformed

    renders_of = _renders(args, ds, ds.split("test"))

    def anchor(scene, q, raw):
        renders = renders_of(scene, q, *raw.shape[1:3])
        return after(torch.from_numpy(raw).permute(0, 3, 1, 2), renders, setting).permute(0, 2, 3, 1).numpy()

    label = _label(setting)
    write_transformed(args.submission, args.write, ds, "-anchor", {"vcm_anchor_bench": label,
                      "transfer": f"bench/vcm_anchor.py --write {label}"}, anchor)


def _screen_submission(args, ds, scenes, seqs, settings, net, gt_feats) -> None:
    """The `after` settings on --submission's frames (module doc): one `report` line each."""
    from vcm_lowpass import submission_frames

    renders_of = _renders(args, ds, scenes)
    rows, feats, seconds = ({s: [] for s in settings} for _ in range(3))
    for s_, q in seqs:
        frames = list(q.frames)
        raw = torch.from_numpy(submission_frames(args.submission, s_, frames)).permute(0, 3, 1, 2).float()
        renders = renders_of(s_, q, *raw.shape[2:])
        pairs = metric_pairs(frames)
        for s in settings:
            t0 = time.perf_counter()
            x = raw if s[0] == "none" else after(raw, renders, s)
            seconds[s].append(time.perf_counter() - t0)
            x = ((x.permute(0, 2, 3, 1).numpy() * 255).round() / 255).astype(np.float32)  # as a submission holds it
            rows[s].append(scored(x, frames, pairs))
            feats[s].append(features(net, x))
    _reports(settings, rows, feats, seconds, gt_feats)


def _reports(settings, rows: dict, feats: dict, seconds: dict, gt_feats: np.ndarray) -> None:
    """One `report` line a setting, paired against the first ("none"), with its seconds."""
    for s in settings:
        print(report(_label(s), np.array(rows[s]), None if s == ("none",) else np.array(rows[("none",)]),
                     np.concatenate(feats[s]), gt_feats) + f"; {sum(seconds[s]):.0f} s", flush=True)


def _label(setting) -> str:
    """A parsed setting written back as its text."""
    if setting[0] == "chain":
        return "+".join(_label(s) for s in setting[1:])
    return ":".join(str(v) for v in setting)


#: The settings applied to finished frames, which --write and --submission take.
AFTER = ("after", "time", "flow", "chain")


def _is_map(target: str) -> bool:
    """[l|o]map, [l|o]mapN (N 2-8), [l|o]mapNwK (K >= 1)."""
    prefix, is_map, rest = target.partition("map")
    tiles, w, k = rest.partition("w")
    return (bool(is_map) and prefix in FITS and tiles in ("", *"2345678")
            and (not w or k.isdigit() and int(k) >= 1))


def parse(text: str):
    """WHERE:SIGMA:MIX[:TARGET[:FROM:TO]], or `after` settings joined by + (module doc) -> a tuple."""
    if "+" in text:
        chain = [parse(t) for t in text.split("+")]
        if all(c[0] in AFTER for c in chain):
            return ("chain", *chain)
    parts = text.split(":")
    if parts[0] == "none" and len(parts) == 1:
        return ("none",)
    try:
        if parts[0] == "after" and len(parts) in (3, 4):
            target = parts[3] if len(parts) == 4 else "render"
            if target in ("render", "carried") or _is_map(target):
                return "after", float(parts[1]), float(parts[2]), target
        if parts[0] == "after" and len(parts) == 5 and _is_map(parts[3]):
            return "after", float(parts[1]), float(parts[2]), parts[3], float(parts[4])
        if parts[0] == "time" and len(parts) == 3:
            return "time", float(parts[1]), float(parts[2])
        if parts[0] == "flow" and len(parts) == 4 and parts[3] in ("mean", "median"):
            return "flow", float(parts[1]), float(parts[2]), parts[3]
        if parts[0] == "sampler" and len(parts) == 6 and (parts[3] == "render" or _is_map(parts[3]) and
                                                          parts[3].startswith("map") and "w" not in parts[3]):
            return "sampler", float(parts[1]), float(parts[2]), parts[3], int(parts[4]), int(parts[5])
    except ValueError:
        pass
    raise argparse.ArgumentTypeError(f"setting {text!r}: expected after:SIGMA:MIX[:render|mapN[wK][:CHROMA]|carried] "
                                     "time:SIGMA:TAU, flow:SIGMA:W:mean|median (joined by + for a chain), sampler:SIGMA:MIX:render|map[N]:FROM:TO "
                                     "or none")


def main(argv=None) -> None:
    ap = screen_parser(__doc__)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a field of the preset for the frames every setting starts from, e.g. vcm_noise=0 "
                         "(independent noise: `skyeyes-no-vcm`'s frames); clip_frames=1 always")
    ap.add_argument("--write", type=Path, default=None, metavar="DIR",
                    help="with --submission and one `after` setting: that submission's frames of every test scene, "
                         "anchored, as a submission here (score it with `skyeyes-bench evaluate DIR`)")
    ap.add_argument("--submission", type=Path, default=None,
                    help="the frames to anchor (a `small` run's): with --write, written anchored; without, the `after` "
                         "settings screened on them (above)")
    ap.add_argument("--anchor-frames", type=Path, default=None, metavar="SUB",
                    help="with --submission: anchor to this submission's frames (e.g. a `gaussians3d` run's, of the "
                         "same test sequences and size) instead of the stage cache's prior renders")
    ap.add_argument("settings", nargs="+", type=parse, help="WHERE:SIGMA:MIX[:TARGET[:FROM:TO]] (above)")
    args = ap.parse_args(argv)
    from skyeyes_bench import paths
    from skyeyes_bench.metrics.inception import load_inception

    ds, scenes, seqs = screened(args)
    if args.write is not None:
        if args.submission is None or len(args.settings) != 1 or args.settings[0][0] not in AFTER:
            ap.error("--write takes --submission and one `after` setting (or a chain of them)")
        return _write(args, ds, args.settings[0])
    if args.anchor_frames is not None and args.submission is None:
        ap.error("--anchor-frames takes --submission (the frames it anchors)")
    if args.submission is not None and any(s[0] == "sampler" for s in args.settings):
        ap.error("--submission screens `after` settings: a `sampler` setting samples frames of its own")
    print(f"{len(seqs)} sequences; --set {' '.join(args.set) or '(none)'}; load average {os.getloadavg()[0]:.1f}",
          flush=True)
    net = load_inception(paths.cache_dir() / "weights" / "inception-2015-12-05-fid-helper-default_1.pt")
    gt_feats = features(net, np.concatenate([np.stack([f.image() for f in q.frames]) for _, q in seqs]))
    settings = [("none",), *[s for s in args.settings if s != ("none",)]]
    if args.submission is not None:
        return _screen_submission(args, ds, scenes, seqs, settings, net, gt_feats)
    config, _ = Skyeyes.configure(args.preset, [*args.set, "clip_frames=1"])
    m = Skyeyes(config, args.workdir / "work", progress=False)
    m.fit_train(ds)
    m.fit_scenes(scenes, progress=False)
    cfg, acm = m.config.core, m.guidance.sampling_model(m.acm)
    rows, feats, seconds = ({s: [] for s in settings} for _ in range(3))
    for s_, q in seqs:
        frames = list(q.frames)
        if frames[0].height != cfg.resolution or frames[0].width != cfg.resolution:
            raise SystemExit(f"{q.id}: frames of {frames[0].width}x{frames[0].height}, expected the model's "
                             f"{cfg.resolution}x{cfg.resolution}")
        priors = [m.scene_model(s_)[frame_key(s_, f)] for f in frames]
        cc = core.encode_cond(to_model(priors, cfg.resolution), cfg, m.device)
        seed = m.sequence_seed(q)  # render_sequence's
        noise = m._start_noise(S.sample_shape(tuple(cc.shape), acm.cfg), seed, priors)
        renders = torch.from_numpy(_guides(priors, cfg.resolution, cfg.resolution)).permute(0, 3, 1, 2)
        pairs = metric_pairs(frames)
        t0 = time.perf_counter()
        sampled = core.decode(core.from_diffused(m._generate(cc, seed, None, priors), cc, cfg), cfg)
        base_s = time.perf_counter() - t0
        for s in settings:
            t0 = time.perf_counter()
            if s[0] == "sampler":
                z = sample_anchored(acm, cc, noise, config.sample_steps, s)
                x = core.decode(core.from_diffused(z, cc, cfg), cfg)
            else:
                x = sampled if s[0] == "none" else after(sampled, renders, s)
            seconds[s].append(time.perf_counter() - t0 + (base_s if s[0] != "sampler" else 0.0))
            x = x.permute(0, 2, 3, 1).numpy()
            rows[s].append(scored(x, frames, pairs))
            feats[s].append(features(net, x))
    _reports(settings, rows, feats, seconds, gt_feats)
    print(f"load average after {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
