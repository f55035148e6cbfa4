"""Throughput of the metrics on this machine, next to the naive figure and the FLOP-bound ceiling.

    .venv/bin/python bench/metrics.py [--images 16] [--clips 2] [--threads N]

Prints frames/s (Inception, LPIPS, SSIM), clips/s (I3D), the naive throughput of calling the
TorchScript Inception directly (batch 1, default settings), and for each network the ceiling
this machine's measured float32 matmul rate allows (GFLOP/s divided by the network's FLOPs per
item, counted with torch.utils.flop_counter). Needs `skyeyes-bench weights fetch`; LPIPS uses
random backbone weights when the torchvision file is absent (same FLOPs, says so).
Other processes on the machine lower every figure: the load average is printed.
"""

from __future__ import annotations

import argparse
import os
import time
import warnings

import numpy as np


def _timeit(fn, reps: int = 1) -> float:
    """Best wall time of `reps` calls (after one warm-up call)."""
    fn()
    best = float("inf")
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def matmul_gflops(torch, n: int = 2048) -> float:
    a, b = torch.rand(n, n), torch.rand(n, n)
    t = _timeit(lambda: torch.mm(a, b), reps=5)
    return 2 * n**3 / t / 1e9


def count_flops(torch, model, x) -> float:
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as fc, torch.inference_mode():
        model(x)
    return float(fc.get_total_flops())


def bench_inception(torch, frames: np.ndarray, gfs: float) -> None:
    """Inception: naive (TorchScript as shipped, batch 1, no_grad, default threads) vs ours."""
    from skyeyes_bench.metrics import weights as W
    from skyeyes_bench.metrics.extractors import get_extractor
    from skyeyes_bench.metrics.inception import preprocess

    n, s = len(frames), frames.shape[1]
    path = W.require("inception-2015-12-05-fid-helper-default_1.pt", "inception-tf-2015")
    raw = torch.jit.load(str(path)).eval()
    x = preprocess(frames).contiguous()
    flops = count_flops(torch, raw, x[:1])

    def naive():
        with torch.no_grad():
            for i in range(n):
                raw(x[i:i + 1])

    t_naive = _timeit(naive)
    ex = get_extractor("inception-tf-2015")
    t_ours = _timeit(lambda: ex.features(frames))
    model = ex.model
    xc = x.contiguous(memory_format=torch.channels_last)

    def ours_model():
        with torch.inference_mode():
            model(xc)

    t_model = _timeit(ours_model)
    print(f"inception-tf-2015: {flops / 1e9:.2f} GFLOP/frame, ceiling {gfs * 1e9 / flops:.1f} frames/s")
    print(f"  naive TorchScript, batch 1:            {n / t_naive:.2f} frames/s")
    print(f"  ours, network only (batch {n}):         {n / t_model:.2f} frames/s  ({t_naive / t_model:.2f}x naive)")
    print(f"  ours, with clean resize {s}->299:      {n / t_ours:.2f} frames/s  ({t_naive / t_ours:.2f}x naive)")


def bench_i3d(torch, clips: np.ndarray, gfs: float) -> None:
    """I3D on `clips` [B, 16, H, W, 3]."""
    from skyeyes_bench.metrics import weights as W
    from skyeyes_bench.metrics.extractors import get_extractor
    from skyeyes_bench.metrics.i3d import load_i3d

    i3d_path = W.require("i3d-kinetics-400.ckpt", "i3d-kinetics400")
    vex = get_extractor("i3d-kinetics400")
    from skyeyes_bench.metrics.extractors import preprocess_clips

    f_i3d = count_flops(torch, load_i3d(i3d_path), preprocess_clips(clips[:1]))
    t_i3d = _timeit(lambda: vex.features(clips))
    print(f"i3d-kinetics400: {f_i3d / 1e9:.1f} GFLOP/clip (16x224x224), ceiling {gfs * 1e9 / f_i3d:.2f} clips/s")
    print(f"  ours (batch {len(clips)}):                    {len(clips) / t_i3d:.3f} clips/s")


def bench_lpips(torch, frames: np.ndarray, gfs: float) -> None:
    """LPIPS (AlexNet): real weights if present, else a random backbone (same FLOPs)."""
    from skyeyes_bench.metrics.extractors import get_extractor
    from skyeyes_bench.metrics.lpips_net import LPIPSNet

    n, s = len(frames), frames.shape[1]
    lex = get_extractor("lpips-alex-v0.1")
    if lex.status()[0] == "present":
        net, note = lex.model, "real weights"
    else:
        torch.manual_seed(0)
        net, note = LPIPSNet("alex").eval().requires_grad_(False), "random backbone (torchvision file absent)"
    a = torch.from_numpy(frames).permute(0, 3, 1, 2) * 2 - 1
    b = a.flip(0)
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as fc, torch.inference_mode():
        net(a[:1], b[:1])
    f_lp = float(fc.get_total_flops())

    def lp():
        with torch.inference_mode():
            net(a, b)

    t_lp = _timeit(lp)
    print(f"lpips-alex-v0.1 ({note}): {f_lp / 1e9:.2f} GFLOP/pair at {s}x{s}, ceiling {gfs * 1e9 / f_lp:.1f} pairs/s")
    print(f"  ours (batch {n}):                      {n / t_lp:.2f} pairs/s")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", type=int, default=16, help="frames per Inception / LPIPS / SSIM batch")
    ap.add_argument("--clips", type=int, default=2, help="16-frame clips per I3D batch")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: OMP_NUM_THREADS or all cores)")
    ap.add_argument("--size", type=int, default=256, help="input frame size (square)")
    args = ap.parse_args()
    if args.threads:
        os.environ["OMP_NUM_THREADS"] = str(args.threads)
    warnings.filterwarnings("ignore")

    import torch

    from skyeyes_bench.metrics import ssim
    from skyeyes_bench.metrics.extractors import torch_setup

    torch_setup()
    print(f"cores {os.cpu_count()}, torch threads {torch.get_num_threads()}, load average "
          f"{' '.join(f'{x:.1f}' for x in os.getloadavg())}, torch {torch.__version__}")
    gfs = matmul_gflops(torch)
    print(f"float32 matmul (2048^3): {gfs:.1f} GFLOP/s")

    rng = np.random.default_rng(0)
    n, s = args.images, args.size
    frames = rng.random((n, s, s, 3)).astype(np.float32)
    bench_inception(torch, frames, gfs)
    bench_i3d(torch, rng.random((args.clips, 16, s, s, 3)).astype(np.float32), gfs)
    bench_lpips(torch, frames, gfs)

    # --- SSIM (numpy, float64)
    t_ss = _timeit(lambda: ssim(frames, frames[::-1]))
    print(f"ssim ({s}x{s}, float64 numpy):           {n / t_ss:.1f} pairs/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
