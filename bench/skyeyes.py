"""Benchmark of the Skyeyes reference method: training speed per module, seconds per generated
frame, and quality (FVD, KVD, LPIPS) against training time at a few ACM checkpoints, on the
validation split (settings are chosen here, never on test: docs/evaluate.md, "The split"; --split test exits 2).

    .venv/bin/python bench/skyeyes.py --preset smoke --acm-steps 50,100,200
    .venv/bin/python bench/skyeyes.py --preset smoke --no-eval       # speed only
    .venv/bin/python bench/skyeyes.py --preset smoke --methods skyeyes-no-vcm --set core.residual=false
    .venv/bin/python bench/skyeyes.py --preset small --data DIR      # another dataset's validation split

The data is --data (default: the SynthTown validation data of --preset, `skyeyes-bench data
synthtown --preset P --split val`, made if absent) as a run on its validation split sees it: the
methods train on its train split and render and score the validation scenes (the submissions
and results say `split: "val"`).

Stages are cached by content hash (`<cache>/reference/diffusion/`) and a longer ACM run
resumes from the shorter one, so the checkpoints cost one ACM training in total. Prints a
table; with --out, also writes the rows as JSON. Quality needs the extractor weights
(`skyeyes-bench weights fetch`); missing metrics print as n/a.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

from reference import screen


def _metric(res: dict, name: str):
    m = res.get("metrics", {}).get(name, {})
    return m.get("value") if m.get("status") == "ok" else None


def run_one(cls, cfg, ds, root: Path, workdir: Path, *, evaluate: bool, seed: int, progress: bool) -> dict:
    """Train `cls` at `cfg` on `ds`'s train split, render its "test" scenes (the validation scenes of
    a `screen.screen_data` view) into a submission in `workdir`, score it against `root`'s data."""
    from skyeyes_bench.submission import SubmissionWriter

    m = cls(cfg, workdir, seed=seed, progress=progress)
    t0 = time.perf_counter()
    m.fit_train(ds)
    fit_train_s = time.perf_counter() - t0
    per_frame, cpu_frame, fit_scene_s = [], [], 0.0
    sub = workdir / "submission"
    with SubmissionWriter(sub, dataset=ds, method=m.name, method_version=m.version, config=m.config_dict(),
                          overwrite=True) as w:
        for scene in ds.split("test"):
            t0 = time.perf_counter()
            m.fit_scene(scene)
            fit_scene_s += time.perf_counter() - t0
            for seq in scene.sequences.values():
                t0, c0 = time.perf_counter(), time.process_time()
                imgs = list(m.render_sequence(scene, seq))
                dt = (time.perf_counter() - t0) / max(len(imgs), 1)
                dc = (time.process_time() - c0) / max(len(imgs), 1)
                for f, img in zip(seq.frames, imgs, strict=True):
                    w.add(scene.name, f, img)
                    per_frame.append(dt)
                    cpu_frame.append(dc)
        w.finish(timings={"fit_s": fit_train_s + fit_scene_s, "render_s": sum(per_frame),
                          "per_frame_render_s": per_frame})
    row = {"method": m.name, "acm_steps": cfg.acm_steps,
           "train_s": sum(v["seconds"] for v in m.training.values()),
           **{f"{k}_it_s": v["it_per_s"] for k, v in m.training.items()},
           **{f"{k}_cpu_s_it": v["cpu_s_per_it"] for k, v in m.training.items()},
           "prior_s": round(fit_scene_s, 2), "s_per_frame": sum(per_frame) / max(len(per_frame), 1),
           "cpu_s_per_frame": sum(cpu_frame) / max(len(cpu_frame), 1)}
    if evaluate:
        from skyeyes_bench.evaluate import evaluate as run_eval

        res = run_eval(sub, data=root, out=workdir / "results.json", force=True, progress=progress)
        row.update({k: _metric(res, k) for k in ("fid", "kid", "fvd", "kvd", "lpips", "psnr")})
    return row


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="smoke", help="method and SynthTown preset (smoke, small)")
    screen.split_options(ap)
    ap.add_argument("--acm-steps", default="", help="comma-separated ACM step counts (default: the preset's)")
    ap.add_argument("--prior", default=None, help="prior method id (default: the preset's, sugar)")
    ap.add_argument("--methods", default="skyeyes,skyeyes-no-vcm", help="comma-separated method ids")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="override a config field (repeatable; dotted for the core: --set core.residual=false)")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    ap.add_argument("--no-eval", action="store_true", help="skip FVD/KVD/LPIPS")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workdir", default="bench-out/skyeyes", help="where submissions and results go")
    ap.add_argument("--out", default=None, help="write the rows as JSON here")
    ap.add_argument("--quiet", action="store_true")
    a = ap.parse_args(argv)
    from skyeyes_bench.splits import screening_split

    screening_split(a.split, "bench/skyeyes.py")  # before anything is imported, made or read

    import torch

    from reference.methods import get_method_class

    if a.threads:
        torch.set_num_threads(a.threads)
    ds = screen.screen_data(a.split, "bench/skyeyes.py", data=a.data, preset=a.preset)
    root = ds.root
    rows = []
    for name in a.methods.split(","):
        cls = get_method_class(name)
        base, _ = cls.configure(a.preset, [*([f"prior_method={a.prior}"] if a.prior else []), *a.overrides])
        steps = [int(s) for s in a.acm_steps.split(",") if s] or [base.acm_steps]
        for k in sorted(steps):
            cfg = dataclasses.replace(base, acm_steps=k)
            tag = "-".join(o.replace("=", "") for o in a.overrides)
            row = run_one(cls, cfg, ds, root, Path(a.workdir) / f"{name}-acm{k}{'-' + tag if tag else ''}",
                          evaluate=not a.no_eval, seed=a.seed, progress=not a.quiet)
            row["overrides"] = " ".join(a.overrides)
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)

    keys = ["method", "overrides", "acm_steps", "train_s", "base_it_s", "acm_it_s", "vcm_it_s", "base_cpu_s_it", "acm_cpu_s_it",
            "vcm_cpu_s_it", "prior_s", "s_per_frame", "cpu_s_per_frame",
            "fid", "kid", "fvd", "kvd", "lpips", "psnr"]
    print(f"# skyeyes bench: preset {a.preset}, {ds.name} {ds.scored} split, {torch.get_num_threads()} threads, "
          f"torch {torch.__version__}")
    print(" | ".join(keys))
    for r in rows:
        print(" | ".join("n/a" if r.get(k) is None else (f"{r[k]:.4g}" if isinstance(r[k], float) else str(r[k]))
                         for k in keys))
    if a.out:
        from skyeyes_bench import outputfiles

        outputfiles.write_json(a.out, rows)


if __name__ == "__main__":
    screen.run_main(main, sys.argv[1:])
