"""Benchmark `skyeyes-bench evaluate` end to end: frames/s and peak RSS for N and 4N frames.

    .venv/bin/python bench/evaluate.py [--frames 128] [--size 64]

Builds synthetic datasets (DatasetWriter; 16-frame sequences) and blurred submissions in a
temporary folder, then evaluates each in a fresh process (so peak RSS is that run's own) under
a bench protocol that keeps every stage of the official ones (PSNR, SSIM, LPIPS, FID, KID, FVD,
KVD; 1000 bootstrap resamples) but uses the test-only `random-*` extractors, which need no
weights. LPIPS is reported unavailable unless its weights are registered. Prints one line per
size; memory should grow only by the per-frame values and features kept (O(N)), not O(N^2).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

PROTOCOL = """
id = "bench"
version = 1
title = "evaluate benchmark"
description = "official stages and statistics, test-only extractors"
reference = "bench/evaluate.py"

[data]
source = "synthtown"
train = ["train-0"]
test = ["test-0"]
width = {size}
height = {size}
fov_deg = 90.0

[capture]
ground_height_m = 2.0
ground_pitch_deg = 0.0
ground_step_m = 2.0
yaws_deg = [0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0]
aerial_height_m = 52.0
aerial_pitch_deg = -45.0
sequence = "bench"

[metrics.psnr]
aggregate = "mean"

[metrics.ssim]
aggregate = "mean"
window = 11
sigma = 1.5
k1 = 0.01
k2 = 0.03

[metrics.lpips]
aggregate = "mean"
extractor = "lpips-alex-v0.1"

[metrics.fid]
extractor = "random-image-64"

[metrics.kid]
extractor = "random-image-64"
subset_size = 1000
num_subsets = 100

[metrics.fvd]
extractor = "random-video-64"
clip_length = 16
clip_stride = 16

[metrics.kvd]
extractor = "random-video-64"
clip_length = 16
clip_stride = 16
subset_size = 1000
num_subsets = 100

[statistics]
bootstrap_resamples = 1000
interval = 0.95
seed = 0
cluster = "sequence"
emcee_walkers = 32
emcee_steps = 3000
emcee_burn = 1000
"""


def child(sub: str, data: str, out: str) -> None:
    from skyeyes_bench.evaluate import evaluate

    t0 = time.perf_counter()
    res = evaluate(sub, data=data, out=out, progress=False)
    wall = time.perf_counter() - t0
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux
    print(json.dumps({"wall_s": wall, "rss_mb": rss_mb, "frames": len(res["frames"]),
                      "timing_s": res["timing_s"],
                      "status": {k: v["status"] for k, v in res["metrics"].items()}}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=128, help="N (rounded to 16-frame sequences); also runs 4N")
    ap.add_argument("--size", type=int, default=64, help="image size in pixels")
    ap.add_argument("--child", nargs=3, metavar=("SUB", "DATA", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(*args.child)
        return
    from builders.evaluation import blurred_submission, make_dataset

    from skyeyes_bench.data.layout import open_dataset

    tmp = Path(tempfile.mkdtemp(prefix="skyeyes-bench-eval-"))
    try:
        protos = tmp / "protocols"
        shutil.copytree(ROOT / "protocols", protos)
        (protos / "bench").mkdir()
        (protos / "bench" / "v1.toml").write_text(PROTOCOL.replace("{size}", str(args.size)))
        env = dict(os.environ, SKYEYES_PROTOCOLS=str(protos), SKYEYES_CACHE=str(tmp / "cache"))
        os.environ.update(SKYEYES_PROTOCOLS=env["SKYEYES_PROTOCOLS"], SKYEYES_CACHE=env["SKYEYES_CACHE"])
        print(f"# evaluate benchmark: {args.size}x{args.size} frames, 16-frame sequences, "
              f"{os.cpu_count()} cores, fresh feature cache per size")
        print(f"{'frames':>7} {'seqs':>5} {'wall s':>8} {'frames/s':>9} {'peak RSS MB':>12}  stages (s)")
        for n in (args.frames, 4 * args.frames):
            seqs = max(1, n // 16)
            scenes = max(1, seqs // 8)
            per_scene = max(1, seqs // scenes)
            root = make_dataset(tmp / f"ds{n}", protocol="bench@1", name=f"bench{n}", scenes=scenes,
                                seqs=per_scene, frames=16, size=args.size)
            ds = open_dataset(root)
            sub = blurred_submission(ds, tmp / f"sub{n}")
            env["SKYEYES_CACHE"] = str(tmp / f"cache{n}")
            p = subprocess.run([sys.executable, __file__, "--child", str(sub), str(root), str(tmp / f"r{n}.json")],
                               env=env, capture_output=True, text=True)
            if p.returncode:
                sys.exit(p.stderr)
            r = json.loads(p.stdout.strip().splitlines()[-1])
            stages = " ".join(f"{k[:-2]}={v:.1f}" for k, v in r["timing_s"].items() if k != "total_s")
            print(f"{r['frames']:>7} {scenes * per_scene:>5} {r['wall_s']:>8.1f} {r['frames'] / r['wall_s']:>9.1f} "
                  f"{r['rss_mb']:>12.0f}  {stages}")
        print("# unavailable: " + (", ".join(k for k, v in r["status"].items() if v != "ok") or "none"))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
