"""The street from one view (`vcm_street`, `warp.street_transfer`) and the sky from one fit
(`vcm_sky`, `warp.sky_fit`; issue 36), screened on a run's frames: each frame's pixels of the
street's plane (under the prior's Gaussians) take the colour of the frame that sees that point
VIEW_M away, and its sky one smooth function of the direction, so the road and the sky hold still
from frame to frame.

    PYTHONPATH= .venv/bin/python bench/vcm_street.py --data ~/.cache/skyeyes-bench/data/synthtown-v2-small \\
        --workdir /tmp/vcm-screen --submission RUN/submission --scenes 1 0.5:0:4 0.6:1:4 0.6:1:0

A setting is ANCHOR:MIX[:VIEW_M[:SKY]]: first the prior anchor at `vcm_anchor_mix` ANCHOR (0:
none; sigma 3 px, a 4 x 4 grid of colour maps: `warp.prior_anchor`, what `vcm_anchor` does) on
the submission's frames, then the street transfer at `vcm_street` MIX (0: none) with the owner
view VIEW_M m away (default `warp.STREET_VIEW_M`; 0: the nearest view), then the sky from one fit
of the sequence's at `vcm_sky` SKY (default 0: none; `warp.sky_fit`). The submission should be a
run without any of the three (the `small` preset's frames before the anchor: carried noise, the
paper's VCM; `reproduce ... --set vcm_anchor=0 --set vcm_street=0 --set vcm_sky=0`), so that each setting is what the pipeline would make from the same sampled frames, up to
the frames' 8-bit rounding.

Scored as bench/vcm_screen.py scores (`report`), each setting's frames rounded to 8 bits: the
warp error against the first setting's, with a 95% bootstrap over sequences, PSNR, LPIPS and the
FID of these frames against their truth (over all 8 test scenes, --scenes 8, the board's FID).
The prior's fitted scenes are read from --workdir's `work/prior/scenes` (link a `reproduce`
run's `method/prior/scenes` there), the conditions from the stage cache.

With --write DIR, the first setting's frames of every test scene go to DIR as a submission for
`skyeyes-bench evaluate`.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import torch

from reference.common.diffusion import warp
from reference.common.diffusion.pipeline import _guides
from reference.common.priors import frame_key
from reference.methods.skyeyes import Skyeyes

sys.path.insert(0, str(Path(__file__).parent))
from vcm_lowpass import submission_frames, write_transformed  # noqa: E402
from vcm_screen import features, metric_pairs, report, screen_parser, screened, scored  # noqa: E402


def parse(text: str) -> tuple[float, float, float, float]:
    """ANCHOR:MIX[:VIEW_M[:SKY]] -> (anchor mix, street mix, view distance, sky mix)."""
    parts = [float(v) for v in text.split(":")]
    if len(parts) not in (2, 3, 4) or not all(0 <= parts[i] <= 1 for i in (0, 1, 3) if i < len(parts)):
        raise SystemExit(f"setting {text!r}: expected ANCHOR:MIX[:VIEW_M[:SKY]], ANCHOR, MIX and SKY in [0, 1]")
    view = parts[2] if len(parts) >= 3 else warp.STREET_VIEW_M
    return parts[0], parts[1], view, parts[3] if len(parts) == 4 else 0.0


class Sequences:
    """What a setting needs of a test sequence besides its frames: the prior's renders (the
    anchor's target), the frames' cameras and prior depths at the frames' size, the street's
    height (the street transfer's)."""

    def __init__(self, args, ds, scenes):
        config, _ = Skyeyes.configure(args.preset, [])
        self.m = Skyeyes(config, args.workdir / "work", progress=False)
        self.m.fit_train(ds)
        self.m.fit_scenes(scenes, progress=False)
        self.zg, self.geometry = {}, {}

    def apply(self, setting, scene, q, raw: np.ndarray) -> np.ndarray:
        """Frames [N, H, W, 3] in [0, 1] -> the same through `setting`."""
        anchor, mix, view_m, sky = setting
        frames = list(q.frames)
        h, w = raw.shape[1:3]
        x = torch.from_numpy(raw).permute(0, 3, 1, 2).float()
        if anchor:
            renders = torch.from_numpy(_guides([self.m.scene_model(scene)[frame_key(scene, f)] for f in frames],
                                               h, w)).permute(0, 3, 1, 2)
            x = warp.prior_anchor(x, renders, 3.0, anchor, 4)
        if mix or sky:
            prior = self.m.prior
            if scene.name not in self.zg:
                prior.fit_scene(scene)  # resumed from its checkpoint
                self.zg[scene.name] = warp.prior_ground(prior, scene)
            if q.id not in self.geometry:  # rendered once a sequence, whichever settings follow
                self.geometry = {q.id: ([warp.scaled_camera(f.camera(), w, h) for f in frames],
                                        [warp.prior_depth(prior, scene, f, w, h) for f in frames])}
            cams, depths = self.geometry[q.id]
            if mix:
                x = warp.street_transfer(x, cams, depths, self.zg[scene.name], mix=mix, view_m=view_m)
            if sky:
                x = warp.sky_fit(x, cams, depths, mix=sky)
        return x.permute(0, 2, 3, 1).numpy()


def main(argv=None) -> None:
    ap = screen_parser(__doc__)
    ap.add_argument("--submission", required=True, type=Path, help="a run's submission folder (before the anchor)")
    ap.add_argument("--write", type=Path, help="write the first setting's frames of every test scene here")
    ap.add_argument("settings", nargs="+", help="ANCHOR:MIX[:VIEW_M[:SKY]] (above)")
    args = ap.parse_args(argv)
    settings = [parse(s) for s in args.settings]
    if args.write is not None:
        ds = screened(args)[0]
        seqs = Sequences(args, ds, ds.split("test"))
        extra = {"vcm_anchor": 3.0, "vcm_anchor_mix": settings[0][0], "vcm_street": settings[0][1],
                 "street_view_m": settings[0][2], "vcm_sky": settings[0][3], "transfer": f"bench/vcm_street.py --write {args.settings[0]}"}
        write_transformed(args.submission, args.write, ds, "-street", extra,
                          lambda scene, q, raw: seqs.apply(settings[0], scene, q, raw))
        return
    from skyeyes_bench import paths
    from skyeyes_bench.metrics.inception import load_inception

    ds, scenes, seqs = screened(args)
    net = load_inception(paths.cache_dir() / "weights" / "inception-2015-12-05-fid-helper-default_1.pt")
    gt_feats = features(net, np.concatenate([np.stack([f.image() for f in q.frames]) for _, q in seqs]))
    parts = Sequences(args, ds, scenes)
    rows, feats, seconds = ({s: [] for s in settings} for _ in range(3))
    for scene, q in seqs:
        frames = list(q.frames)
        raw = submission_frames(args.submission, scene, frames)
        pairs = metric_pairs(frames)
        for s in settings:
            t0 = time.perf_counter()
            x = parts.apply(s, scene, q, raw)
            seconds[s].append(time.perf_counter() - t0)
            x = ((x * 255).round() / 255).astype(np.float32)  # as a submission holds it
            rows[s].append(scored(x, frames, pairs))
            feats[s].append(features(net, x))
    for i, s in enumerate(settings):
        print(report(args.settings[i], np.array(rows[s]), None if i == 0 else np.array(rows[settings[0]]),
                     np.concatenate(feats[s]), gt_feats) + f"; {sum(seconds[s]):.0f} s", flush=True)


if __name__ == "__main__":
    main()
