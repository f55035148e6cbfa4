"""Benchmark `skyeyes-bench evaluate` end to end: frames/s and peak RSS for N and 4N frames.

    .venv/bin/python bench/evaluate.py [--frames 128] [--size 64]

Builds synthetic datasets (DatasetWriter; 16-frame sequences) and blurred submissions in a
temporary folder, then evaluates each in a fresh process (so peak RSS is that run's own) under
a bench protocol made from synthtown@2's file (every metric and the statistics: 1000
resamples) with the test-only `random-*` extractors, which need no weights. LPIPS is reported unavailable unless its weights are registered. Prints one line per
size; memory should grow only by the per-frame values and features kept (O(N)), not O(N^2).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def bench_protocol(size: int) -> str:
    """The current SynthTown protocol's text (every metric, its parameters and statistics) with
    the test-only `random-*` extractors in place of Inception and I3D, this benchmark's image size,
    and sequence clusters (the synthetic datasets here have one scene)."""
    text = (ROOT / "protocols" / "synthtown" / "v2.toml").read_text()
    subs = [(r'^id = .*$', 'id = "bench"'), (r'^version = .*$', "version = 1"),
            (r'^(width|height) = .*$', rf"\1 = {size}"), (r'^default_location = .*\n', ""),
            (r'^extractor = "inception-tf-2015"$', 'extractor = "random-image-64"'),
            (r'^extractor = "i3d-kinetics400"$', 'extractor = "random-video-64"'),
            (r'^resize = .*\n', ""), (r'^cluster = .*$', 'cluster = "sequence"')]
    for pat, rep in subs:
        text, n = re.subn(pat, rep, text, flags=re.M)
        assert n, pat  # the protocol file changed shape: update this list
    return text


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
    from skyeyes_bench.data.layout import open_dataset
    from skyeyes_bench.synthetic import blurred_submission, make_dataset

    tmp = Path(tempfile.mkdtemp(prefix="skyeyes-bench-eval-"))
    try:
        protos = tmp / "protocols"
        shutil.copytree(ROOT / "protocols", protos)
        (protos / "bench").mkdir()
        (protos / "bench" / "v1.toml").write_text(bench_protocol(args.size))
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
