"""Screen settings of a diffusion method (default `skyeyes`) on the validation split before a
whole `reproduce`: the stages come from the stage cache (the ACM and VCM a `reproduce` of the
preset left there; where they are missing they are trained first, as `reproduce` would, which at
`small` takes hours here), and each setting's frames are scored on the warp error, PSNR, LPIPS and
the FID of those frames against the same sequences' truth (comparable between settings here, not
with a protocol's FID), the warp error and LPIPS paired per sequence against the first setting's.
Settings are chosen here, never on test (docs/evaluate.md, "The split"): --split test exits 2.

    .venv/bin/python bench/vcm_screen.py --scenes 2 "" "vcm_steps=6000" "clip_frames=4"
    .venv/bin/python bench/vcm_screen.py --method skyeyes-geo --scenes 2 "" "noise.share=0.5"

A setting is `--set` overrides of --method at --preset (default small), separated by spaces.
Prints the load average before and after.
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

from reference import screen


def main(argv=None) -> None:
    ap = screen.screen_parser(__doc__)
    ap.add_argument("--method", default="skyeyes", help="a diffusion method of the registry (default skyeyes)")
    ap.add_argument("--fvd", action="store_true", help="also the FVD of each setting's frames (I3D on 16-frame clips)")
    ap.add_argument("settings", nargs="+", help='each a setting: `--set` overrides separated by spaces, e.g. '
                    '"vcm_steps=6000"; the first is the one the others are paired against ("": the preset)')
    args = ap.parse_args(argv)
    from reference.methods import get_method_class

    cls = get_method_class(args.method)
    configs = [cls.configure(args.preset, s.split())[0] for s in args.settings]  # each checked before any work
    ds, scenes, seqs = screen.screened(args, "bench/vcm_screen.py")
    print(f"{len(seqs)} sequences of {len(scenes)} {ds.name} val scenes; load average {os.getloadavg()[0]:.1f}",
          flush=True)
    pairs = {q.id: screen.metric_pairs(list(q.frames)) for _, q in seqs}
    gts = [np.stack([f.image() for f in q.frames]) for _, q in seqs]
    gt_feats = screen.features(np.concatenate(gts))
    gt_clips = np.concatenate([screen.clip_features(g) for g in gts]) if args.fvd else None
    rows = {}
    for setting, config in zip(args.settings, configs):
        m = cls(config, args.workdir / "work", progress=False)
        m.fit_train(ds)
        m.fit_scenes(scenes, progress=False)
        t0, c0 = time.perf_counter(), time.process_time()
        per, frames_out = [], []
        for s, q in seqs:
            x = np.stack(list(m.render_sequence(s, q)))
            per.append(screen.scored(x, list(q.frames), pairs[q.id]))  # scoring inside: LPIPS's seconds too
            frames_out.append(x)
        took, cpu = time.perf_counter() - t0, time.process_time() - c0
        rows[setting] = np.array(per)
        line = screen.report(f"[{setting or 'preset'}]", rows[setting], rows[args.settings[0]] if len(rows) > 1 else None,
                             screen.features(np.concatenate(frames_out)), gt_feats)
        if args.fvd:
            line += f"; FVD (these frames) {screen.fid(np.concatenate([screen.clip_features(x) for x in frames_out]), gt_clips):.0f}"
        print(f"{line}; {stage_seconds(getattr(m, 'training', {}))}; render and score {took:.0f} s ({cpu:.0f} CPU-s)",
              flush=True)
    print(f"load average after {os.getloadavg()[0]:.1f}")


def stage_seconds(training: dict) -> str:
    """The VCM stage's cost as it was trained (a stage from the cache at its original seconds)."""
    v = training.get("vcm")
    if not v:
        return "no VCM stage"
    return f"VCM {v['steps']} steps {v['seconds']:.0f} s ({v.get('cpu_seconds', float('nan')):.0f} CPU-s)"


if __name__ == "__main__":
    screen.run_main(main, sys.argv[1:])
