"""Benchmarks of the compact Instant-NGP (issue 17). Prints figures; not a test.

    python bench/nerf.py speed                  # training and rendering rays/s, threads 1 and 2
    python bench/nerf.py speed --preset small --views 4 --size 128
    python bench/nerf.py fit --data DIR --preset smoke --set init=none   # held-out aerial / ground
                                                # PSNR against training seconds, lane 0

Caveat: the machine has 2 cores shared with other jobs; the load average is printed beside every
figure, and figures vary by tens of percent with it.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path


def _scene_model(preset: str, sets: list[str], views: int, size: int):
    """A model of the preset's field over a synthetic box, and synthetic aerial-like rays."""
    import numpy as np
    import torch

    from reference.common.nerf import Model, NeRFField, OccupancyGrid, SceneBox, camera_rays
    from reference.methods.nerf import NeRF
    from skyeyes_bench.cameras import Camera

    cfg, _ = NeRF.configure(preset, sets)
    box = SceneBox(np.array([-40.0, -40, -1]), np.array([40.0, 40, 40]))
    fld = NeRFField(cfg.field_config())
    grid = OccupancyGrid(cfg.occ_res, step_m=cfg.inner_step(box), alpha=cfg.occ_alpha)
    model = Model(fld, grid, box, torch.tensor([0.6, 0.7, 0.9]))
    rng = np.random.default_rng(0)
    cams = [Camera.from_ypr([x, y, 52.0], yaw, -45, fov_deg=60, width=size, height=size)
            for x, y, yaw in zip(rng.uniform(-30, 30, views), rng.uniform(-30, 30, views), rng.uniform(0, 360, views))]
    imgs = [rng.random((size, size, 3)).astype(np.float32) for _ in cams]
    return cfg, model, camera_rays(cams, imgs, "cpu"), cams


def speed(args) -> None:
    import dataclasses

    import torch

    from reference.common.nerf import render_camera, train

    for threads in (1, 2):
        torch.set_num_threads(threads)
        cfg, model, rays, cams = _scene_model(args.preset, args.set, args.views, args.size)
        cfg = dataclasses.replace(cfg, iterations=args.iterations)
        stats = train(model, rays, cfg, progress=False)
        t0 = time.perf_counter()
        render_camera(model, cams[0], cfg, near=cfg.render_near_m, far_field=False)
        dt = time.perf_counter() - t0
        print(json.dumps({"preset": args.preset, "threads": threads, "batch_rays": cfg.batch_rays,
                          "train_rays_per_s": round(stats["train_rays_per_s"]),
                          "samples_per_ray": round(stats["samples_per_ray"], 1),
                          "render_rays_per_s": round(args.size ** 2 / dt),
                          "load": [round(x, 1) for x in os.getloadavg()]}), flush=True)


def fit(args) -> None:
    """Held-out aerial PSNR (every 4th view held out) and ground PSNR of lane 0 against seconds."""
    import numpy as np
    import torch

    from reference.methods.nerf import NeRF
    from skyeyes_bench.data.layout import open_dataset

    torch.set_num_threads(args.threads)
    ds = open_dataset(Path(args.data))
    scene = ds.split("test")[0]
    config, _ = NeRF.configure(args.preset, [*args.set, "holdout_every=4"])
    m = NeRF(config, Path(args.work) / f"{time.time():.0f}", progress=False)
    m.fit_train(ds)
    held = [f for i, f in enumerate(scene.aerial) if i % 4 == 3]
    ground = [f for s in scene.sequences.values() for f in list(s)[:: args.ground_stride]]

    def psnr(a, b):
        return float(10 * np.log10(1 / np.mean((a - b) ** 2)))

    def callback(it, seconds, model):
        m._scene_models[scene.name] = model
        with torch.no_grad():
            aer = np.mean([psnr(m.render_frame(scene, f, ground=False), f.image()) for f in held])
            gnd = np.mean([psnr(m.render_frame(scene, f), f.image()) for f in ground])
        print(json.dumps({"iteration": it, "train_s": round(seconds, 1), "heldout_aerial_psnr": round(aer, 2),
                          "ground_psnr": round(gnd, 2), "ground_frames": len(ground),
                          "load": round(os.getloadavg()[0], 1)}), flush=True)

    _, stats = m.fit_scene_model(scene, progress=False, callback=callback)
    print(json.dumps({k: v for k, v in stats.items() if not isinstance(v, list)}), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("speed")
    s.add_argument("--preset", default="smoke")
    s.add_argument("--views", type=int, default=4)
    s.add_argument("--size", type=int, default=48)
    s.add_argument("--iterations", type=int, default=20)
    s.add_argument("--set", action="append", default=[])
    f = sub.add_parser("fit")
    f.add_argument("--data", required=True)
    f.add_argument("--preset", default="smoke")
    f.add_argument("--set", action="append", default=[])
    f.add_argument("--threads", type=int, default=1)
    f.add_argument("--ground-stride", type=int, default=4)
    f.add_argument("--work", default="/tmp/bench-nerf")
    args = ap.parse_args()
    {"speed": speed, "fit": fit}[args.cmd](args)


if __name__ == "__main__":
    main()
