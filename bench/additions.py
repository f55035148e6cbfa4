"""Screen the settings of our additions' steps after sampling (the prior anchor, the street from
one view, the sky from one fit: `reference.common.diffusion.additions`) on the validation split:
each setting applied to the same sampled frames of a `reproduce --split val` run, scored against
their truth. Settings are chosen here, never on test (docs/evaluate.md, "The split"): --split test exits 2.

    skyeyes-bench reproduce --method skyeyes-geo --preset small --split val \\
        --set anchor.mix=0 --set street.mix=0 --set sky.mix=0 --out runs/geo-noise-val
    .venv/bin/python bench/additions.py --run runs/geo-noise-val \\
        "" "anchor.mix=0.5" "anchor.mix=0.5 street.mix=0.8" "anchor.mix=0.5 street.mix=0.8 sky.mix=1"

--run: a `reproduce --split val` output folder whose steps after sampling were off (its frames
are what the steps start from; its starting noise is the run's: carried or not). A setting is
`--set` overrides of `skyeyes-geo`'s config with every step after sampling off first, separated
by spaces ("" : none of them), e.g. "anchor.mix=0.6 anchor.sigma_px=4 street.view_m=6 sky.mix=1".

Per setting, one line: the warp error (pooled, and paired against the first setting with a 95%
bootstrap over sequences), PSNR, LPIPS, the FID of the screened frames against their truth and,
with --fvd, their FVD (I3D on 16-frame clips), the seconds the steps took, and the steps that
stepped aside (their assumption checks). Frames are rounded to 8 bits first, as a submission
holds them. Prints the load average before and after.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from reference import screen
from skyeyes_bench.errors import UserError

#: Every step after sampling off: what a setting's overrides start from.
OFF = ("anchor.mix=0", "street.mix=0", "sky.mix=0")


def setting_additions(preset: str, setting: str):
    """The steps after sampling (`Additions.post`) of `skyeyes-geo` at `preset` with every step off,
    then `setting`'s overrides."""
    from reference.common.diffusion.additions import Additions
    from reference.methods.skyeyes_geo import SkyeyesGeo

    config, _ = SkyeyesGeo.configure(preset, [*OFF, *setting.split()])
    return Additions.of(config).post


def run_inputs(run: Path) -> tuple[Path, Path | None, dict]:
    """(the run's submission folder, its prior's fitted scenes or None, its config.json) of a
    `reproduce --split val` output folder; a UserError for anything else."""
    from skyeyes_bench import inputfiles

    cfg_file = run / "config.json"
    if not cfg_file.is_file():
        raise UserError(f"{run}: no config.json (expected a `skyeyes-bench reproduce` output folder)")
    cfg = inputfiles.read_json(cfg_file, allow_nan=True)
    split = (cfg.get("dataset") or {}).get("split", "test")
    if split != "val":
        raise UserError(f"{cfg_file}: field 'dataset.split' is {split!r}: the run screened must be on the validation "
                        "split (`reproduce --split val`)")
    adds = {k: (cfg.get("config") or {}).get(k, {}).get("mix", 0) for k in ("anchor", "street", "sky")}
    if any(adds.values()):
        raise UserError(f"{cfg_file}: the run's steps after sampling were on ({adds}); screen a run made with "
                        "--set anchor.mix=0 --set street.mix=0 --set sky.mix=0")
    scenes = run / "work" / cfg["cache_key"] / "method" / "prior" / "scenes"
    return run / "submission", scenes if scenes.is_dir() else None, cfg


class Prior:
    """The run's prior (its fitted scenes, linked into the screen's work folder) and its renders of
    each screened sequence: what a `SequenceView` needs."""

    def __init__(self, args, cfg: dict, scenes_dir: Path | None, scenes):
        from reference.common.diffusion.conditions import PriorRenders
        from reference.common.priors import prior_part

        c = cfg["config"]
        work = args.workdir / "prior"
        work.mkdir(parents=True, exist_ok=True)
        if scenes_dir is None:
            print("note: no fitted prior scenes given (--prior-scenes) or in the run: the prior is fitted on the "
                  "screened scenes first", flush=True)
        elif not (work / "scenes").exists():
            (work / "scenes").symlink_to(scenes_dir.resolve(), target_is_directory=True)
        self.prior = prior_part(c["prior_method"], c["prior_preset"], work, cfg["seed"], "cpu")
        self.renders = PriorRenders(lambda: self.prior)
        self.renders.fit_scenes(scenes, progress=False, jobs=1)
        self.prior.fit_scenes(scenes, progress=False)  # resumed from the run's checkpoints

    def view(self, scene, q):
        from reference.common.diffusion.additions import SequenceView
        from reference.common.priors import frame_key

        conds = self.renders.of_scene(scene)
        return SequenceView(self.prior, scene, q, [conds[frame_key(scene, f)] for f in q.frames])


def main(argv=None) -> None:
    ap = screen.screen_parser(__doc__)
    ap.add_argument("--run", required=True, type=Path, help="a `reproduce --split val` output folder (above)")
    ap.add_argument("--prior-scenes", type=Path, help="the fitted scenes of the run's prior (default: the run's own, "
                    "RUN/work/KEY/method/prior/scenes; a run whose prior renders came from the cache has none: "
                    "give another run's on the same data, or the prior is fitted again)")
    ap.add_argument("--fvd", action="store_true", help="also the FVD of each setting's frames (I3D: slower)")
    ap.add_argument("settings", nargs="+", help="each a setting (above); the first is the one the others pair against")
    args = ap.parse_args(argv)
    sub, scenes_dir, cfg = run_inputs(args.run)
    scenes_dir = args.prior_scenes or scenes_dir
    if args.data is None:
        args.data = Path(cfg["dataset"]["root"])
    ds, scenes, seqs = screen.screened(args, "bench/additions.py")
    steps = {s: setting_additions(args.preset, s) for s in args.settings}  # each checked before any work
    print(f"{len(seqs)} sequences of {len(scenes)} {ds.name} val scenes; load average {os.getloadavg()[0]:.1f}",
          flush=True)
    from skyeyes_bench.imagefiles import read_image

    prior = Prior(args, cfg, scenes_dir, scenes)
    gts = [np.stack([f.image() for f in q.frames]) for _, q in seqs]
    gt_feats = screen.features(np.concatenate(gts))
    gt_clips = np.concatenate([screen.clip_features(g) for g in gts]) if args.fvd else None
    rows, feats, clips, seconds, aside = ({s: [] for s in args.settings} for _ in range(5))
    for (scene, q), gt in zip(seqs, gts):
        raw = np.stack([read_image(sub / scene.name / f.file) for f in q.frames])
        pairs = screen.metric_pairs(list(q.frames))
        view = prior.view(scene, q)
        for s in args.settings:
            t0 = time.perf_counter()
            x = torch.from_numpy(raw).permute(0, 3, 1, 2).float()
            for step in steps[s]:
                before = x
                x = step(x, view)
                if x is before:
                    aside[s].append(f"{step.name} on {q.id}")
            seconds[s].append(time.perf_counter() - t0)
            x = (x.permute(0, 2, 3, 1).numpy() * 255).round() / 255  # as a submission holds it
            rows[s].append(screen.scored(x.astype(np.float32), list(q.frames), pairs))
            feats[s].append(screen.features(x.astype(np.float32)))
            if args.fvd:
                clips[s].append(screen.clip_features(x.astype(np.float32)))
    base = np.array(rows[args.settings[0]])
    for i, s in enumerate(args.settings):
        line = screen.report(f"[{s or 'none'}]", np.array(rows[s]), None if i == 0 else base,
                             np.concatenate(feats[s]), gt_feats)
        if args.fvd:
            line += f"; FVD (these clips) {screen.fid(np.concatenate(clips[s]), gt_clips):.1f}"
        line += f"; {sum(seconds[s]):.0f} s"
        if aside[s]:
            line += f"; stepped aside: {len(aside[s])} ({aside[s][0]}, ...)"
        print(line, flush=True)
    print(f"load average after {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    screen.run_main(main, sys.argv[1:])
