"""Benchmark `evaluate --ray`: wall time of one submission's evaluation with 1, 2 and 4 Ray workers
against one process, the per-shard costs, and whether the numbers are identical.

    nice -n 10 .venv/bin/python bench/scale.py [--workers 1,2,4] [--shards 8] [--data DIR]

The submission is a blurred copy of the SynthTown `smoke` test split (128 frames, 8 sequences of
16, synthtown@1: PSNR, SSIM, LPIPS, FID, KID, FVD, KVD with the real weights where `weights fetch`
put them, unavailable otherwise). Each run starts from an empty feature cache, so every feature is
computed; each Ray run starts its own local Ray with `--workers` CPUs (one task per CPU, one torch
thread per task); one process runs twice, on every core and on one thread (OMP_NUM_THREADS=1), and
each Ray result is compared with both (I3D's oneDNN convolutions round differently on 1 and 2
threads, docs/scale.md). Speed-up is against the one-thread process. The shards are the same for every worker
count (default 4, two sequences each), so the per-shard cost is one number and a cluster's wall time
is projected as

    wall ≈ Ray start + ceil(shards / workers) × per-shard + merge

Prints the machine's load (`uptime`) before and after: figures measured beside other work say so.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def fresh_cache(path: Path, weights: Path) -> None:
    """An empty cache at `path` holding (links to) the metric weights, used from here on."""
    (path / "weights").mkdir(parents=True)
    for f in weights.glob("*") if weights.is_dir() else []:
        (path / "weights" / f.name).symlink_to(f)
    os.environ["SKYEYES_CACHE"] = str(path)


def load() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def one_process(sub: Path, data: Path, out: Path, threads: str | None) -> tuple[float, dict]:
    """`evaluate` here with every core (threads None) or OMP_NUM_THREADS=threads."""
    from skyeyes_bench.evaluate import evaluate

    old = os.environ.pop("OMP_NUM_THREADS", None)
    if threads:
        os.environ["OMP_NUM_THREADS"] = threads  # `threads.set_threads` reads it before each extractor
    try:
        t0 = time.perf_counter()
        res = evaluate(sub, data=data, out=out, progress=False)
        return time.perf_counter() - t0, res
    finally:
        os.environ.pop("OMP_NUM_THREADS", None)
        if old is not None:
            os.environ["OMP_NUM_THREADS"] = old


def differs(a: dict, b: dict) -> str:
    """'' when the scores are identical, else each metric whose value differs and by how much."""
    from skyeyes_bench.synthetic import comparable

    if comparable(a) == comparable(b):
        return ""
    out = []
    for name, m in a["metrics"].items():
        v, w = m.get("value"), b["metrics"][name].get("value")
        if v != w:
            out.append(f"{name} {abs(v - w) / max(abs(v), 1e-300):.1e}")
        elif m != b["metrics"][name]:
            out.append(f"{name} (interval)")
    return "; ".join(out) or "per-frame or per-sequence values"


def on_ray(sub: Path, data: Path, out: Path, workers: int, shards: int) -> dict:
    from skyeyes_bench import ray_exec
    from skyeyes_bench.batch import Job

    t0 = time.perf_counter()
    with ray_exec.session(num_cpus=workers):
        started = time.perf_counter()
        got = ray_exec.evaluate_many([Job(sub, out, data=str(data))], shards=shards, progress=False)[0]
        done = time.perf_counter()
    if got["error"]:
        sys.exit(f"evaluate on Ray failed: {got['error']}")
    return {"start_s": started - t0, "wall_s": done - started, "shard_s": got["shard_s"], "merge_s": got["merge_s"],
            "results": got["results"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workers", default="1,2,4", help="Ray worker counts (CPUs of each local Ray), comma-separated")
    ap.add_argument("--shards", type=int, default=4, help="shards per evaluation (default 4: two smoke sequences, so two "
                    "I3D clips, a whole batch, per call; 8 gives one clip a call, padded to two)")
    ap.add_argument("--data", type=Path, help="a SynthTown smoke dataset (default: generated into a temporary folder)")
    ap.add_argument("--weights", type=Path, default=None, help="metric weights folder (default: the user's cache's)")
    args = ap.parse_args()
    from skyeyes_bench import paths
    from skyeyes_bench.data.layout import open_dataset
    from skyeyes_bench.synthetic import blurred_submission

    weights = args.weights or paths.weights_dir()
    workers = [int(w) for w in args.workers.split(",")]
    tmp = Path(tempfile.mkdtemp(prefix="skyeyes-bench-scale-"))
    try:
        print(f"# load before: {load()}")
        print(f"# {os.cpu_count()} cores; weights from {weights}; fresh feature cache per run")
        fresh_cache(tmp / "cache-data", weights)
        if args.data is None:
            from skyeyes_bench.data.synthtown import generate_dataset

            args.data = generate_dataset(tmp / "synthtown-smoke", preset="smoke", progress=False)
        ds = open_dataset(args.data)
        sub = blurred_submission(ds, tmp / "sub")
        base = {}
        for threads in (None, "1"):
            fresh_cache(tmp / f"cache-one-{threads}", weights)
            wall, base[threads] = one_process(sub, args.data, tmp / f"one-{threads}.json", threads)
            print(f"one process, {'every core' if threads is None else 'one thread'}: {wall:.1f} s")
        wall1 = wall  # the one-thread process: what a single worker does
        ok = [k for k, m in base[None]["metrics"].items() if m["status"] == "ok"]
        print(f"# {len(base[None]['frames'])} frames, {len(ds.sequences('test'))} sequences; scored: {', '.join(ok)}")
        print(f"# one thread vs every core: {differs(base['1'], base[None]) or 'identical'}")
        print(f"{'workers':>7} {'shards':>6} {'Ray start s':>11} {'evaluate s':>10} {'per shard s (mean/max)':>23} "
              f"{'merge s':>7} {'speed-up':>8}  identical to one process (one thread; every core)")
        rows = []
        for w in workers:
            fresh_cache(tmp / f"cache-{w}", weights)
            r = on_ray(sub, args.data, tmp / f"ray{w}.json", w, args.shards)
            same = [differs(r["results"], base[t]) or "yes" for t in ("1", None)]
            per = r["shard_s"]
            print(f"{w:>7} {len(per):>6} {r['start_s']:>11.1f} {r['wall_s']:>10.1f} "
                  f"{sum(per) / len(per):>11.1f} / {max(per):>9.1f} {r['merge_s']:>7.2f} {wall1 / r['wall_s']:>7.2f}x  "
                  f"{same[0]}; {same[1]}")
            rows.append((w, r))
        w1 = dict(rows).get(1) or rows[0][1]
        per = sum(w1["shard_s"]) / len(w1["shard_s"])
        frames = len(base[None]["frames"]) / args.shards
        print(f"# projection: wall ≈ {w1['start_s']:.0f} s start + ceil(shards / workers) × {per:.1f} s per shard of "
              f"{frames:.0f} frames ({per / frames:.2f} s a frame on one CPU here) + merge ({w1['merge_s']:.1f} s for "
              f"{len(base[None]['frames'])} frames; it grows with the frames: bootstrap of the set metrics)")
        print(f"# load after: {load()}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
