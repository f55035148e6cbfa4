"""Benchmarks of the compact Instant-NGP (issue 17). Prints figures; not a test.

    python bench/nerf.py speed                  # training and rendering rays/s (field and baked)
    python bench/nerf.py speed --preset small --views 4 --size 128
    python bench/nerf.py render --preset small  # a fitted lane's ground frames: field
                                                # renderer against bakes (spacing, view): rays/s,
                                                # agreement, ground PSNR / LPIPS
    python bench/nerf.py fit --preset small --set iterations=600   # held-out aerial
                                                # PSNR, ground PSNR / LPIPS against training seconds
    python bench/nerf.py fit --data DIR --preset small   # another dataset's validation split

`render` and `fit` choose settings, so they run on the validation split (docs/evaluate.md, "The split"; --split
test exits 2): validation lane 0 (`--lane`) of --data (default: the SynthTown validation data of
--preset, `skyeyes-bench data synthtown --preset P --split val`, made if absent), the appearance
learned on what a run on that split trains on; `render` keeps its fit in `--work` and reuses it.
Caveat: the machine has 2 cores shared with other jobs; the load average is printed beside every
figure, and figures vary by tens of percent with it.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from reference import screen
from skyeyes_bench.errors import UserError


def _load() -> list[float]:
    return [round(x, 1) for x in os.getloadavg()]


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
    ground = Camera.from_ypr([0.0, 0.0, 2.0], 30.0, 0.0, fov_deg=90, width=size, height=size)
    return cfg, model, camera_rays(cams, imgs, "cpu"), cams, ground


def speed(args) -> None:
    """Synthetic random views (nothing is ever pruned: the worst case for the field renderer)."""
    import dataclasses

    import torch

    from reference.common.nerf import bake_field, render_baked_camera, render_camera, train

    for threads in args.threads:
        torch.set_num_threads(threads)
        cfg, model, rays, cams, ground = _scene_model(args.preset, args.set, args.views, args.size)
        cfg = dataclasses.replace(cfg, iterations=args.iterations)
        stats = train(model, rays, cfg, progress=False)
        t0 = time.perf_counter()
        render_camera(model, ground, cfg, near=cfg.render_near_m, far_field=False)
        dt_field = time.perf_counter() - t0
        t0 = time.perf_counter()
        baked = bake_field(model.field, model.box, voxel_m=cfg.bake_voxel_m, view="horizontal", grid=model.grid)
        dt_bake = time.perf_counter() - t0
        t0 = time.perf_counter()
        for _ in range(args.repeat):
            render_baked_camera(baked, ground, n_samples=cfg.bake_samples or cfg.n_inner, near=cfg.render_near_m)
        dt_baked = (time.perf_counter() - t0) / args.repeat
        print(json.dumps({"preset": args.preset, "threads": threads, "batch_rays": cfg.batch_rays,
                          "train_rays_per_s": round(stats["train_rays_per_s"]),
                          "samples_per_ray": round(stats["samples_per_ray"], 1),
                          "field_render_rays_per_s": round(args.size ** 2 / dt_field),
                          "bake_s": round(dt_bake, 2), "bake_shape": list(baked.shape),
                          "baked_render_rays_per_s": round(args.size ** 2 / dt_baked), "load": _load()}), flush=True)


def _method(args, extra: list[str], work: Path):
    """(the dataset as a run on --split sees it, its validation lane --lane, the method fitted on its train)."""
    from reference.methods.nerf import NeRF

    config, _ = NeRF.configure(args.preset, [*args.set, *extra])  # checked before any data is made
    ds = screen.screen_data(args.split, f"bench/nerf.py {args.cmd}", data=args.data, preset=_data_preset(args.preset))
    lanes = ds.split("test")
    if not 0 <= args.lane < len(lanes):
        raise UserError(f"--lane {args.lane}: the {ds.scored} split of {ds.name} has {len(lanes)} lanes")
    scene = lanes[args.lane]
    m = NeRF(config, work, progress=False)
    m.fit_train(ds)
    return ds, scene, m


def _data_preset(preset: str) -> str:
    """The SynthTown preset whose data a method preset runs on (the method presets beyond smoke and
    paper run on small's)."""
    return preset if preset in ("smoke", "small", "paper") else "small"


def _psnr(a, b) -> float:
    import numpy as np

    from skyeyes_bench.metrics.image import psnr

    return float(psnr(np.asarray(a, np.float32), np.asarray(b, np.float32)))


def _lpips(preds, gts) -> float | None:
    import numpy as np

    from skyeyes_bench.metrics.image import lpips
    from skyeyes_bench.metrics.weights import MetricUnavailable

    try:
        return float(np.mean(lpips(np.stack(preds), np.stack(gts))))
    except MetricUnavailable:
        return None


def _ground_frames(scene, per_sequence: int) -> list:
    """`per_sequence` frames spread evenly over each of the lane's sequences."""
    import numpy as np

    out = []
    for seq in scene.sequences.values():
        frames = list(seq)
        out += [frames[i] for i in np.linspace(0, len(frames) - 1, per_sequence).round().astype(int)]
    return out


def _mean_frame(ds):
    import numpy as np

    frames = [f for seq in ds.sequences("train") for f in seq]
    return np.mean([f.image() for f in frames], 0).astype(np.float32)


def render(args) -> None:
    """Field renderer against bakes on one fitted lane's ground frames."""
    import dataclasses

    import numpy as np
    import torch

    from reference.common.nerf import bake_field

    torch.set_num_threads(args.threads)
    ds, scene, m = _method(args, ["renderer=field"], Path(args.work))
    # the bake's vertices lie around the lane's ground cameras, as the method's own bake places them
    centres = torch.tensor(np.unique(np.array([f.c2w[:3, 3] for f in scene.ground]), axis=0), dtype=torch.float32)
    m.fit_scene(scene)  # checkpointed in --work: a second run reuses the fit
    model = m.scene_model(scene)
    frames = _ground_frames(scene, args.per_sequence)
    gts = [f.image() for f in frames]
    rays = len(frames) * frames[0].width * frames[0].height
    floor = _mean_frame(ds)
    print(json.dumps({"lane": scene.name, "frames": len(frames), "fit": m.scene_stats[scene.name].get("train_seconds"),
                      "floor_psnr": round(np.mean([_psnr(floor, g) for g in gts]), 2),
                      "floor_lpips": _lpips([floor] * len(gts), gts)}), flush=True)
    t0 = time.perf_counter()
    field = [m.render_frame(scene, f, model=model) for f in frames]
    dt = time.perf_counter() - t0
    print(json.dumps({"renderer": "field", "rays_per_s": round(rays / dt), "seconds": round(dt, 1),
                      "ground_psnr": round(np.mean([_psnr(p, g) for p, g in zip(field, gts)]), 2),
                      "ground_lpips": _lpips(field, gts), "load": _load()}), flush=True)
    for voxel in args.voxels:
        for view in args.views:
            for samples in args.samples:
                m.config = dataclasses.replace(m.config, renderer="baked", bake_voxel_m=voxel, bake_view=view,
                                               bake_samples=samples)
                model.baked = None
                t0 = time.perf_counter()
                model.baked = bake_field(model.field, model.box, voxel_m=voxel, view=view,
                                         centres=centres.to(model.background.device), grid=model.grid)
                t_bake = time.perf_counter() - t0
                t0 = time.perf_counter()
                baked = [m.render_frame(scene, f, model=model) for f in frames]
                dt = time.perf_counter() - t0
                print(json.dumps({"renderer": "baked", "voxel_m": voxel, "view": view,
                                  "samples": samples or m.config.n_inner, "shape": list(model.baked.shape),
                                  "bake_s": round(t_bake, 1), "rays_per_s": round(rays / dt),
                                  "seconds": round(dt, 1),
                                  "psnr_vs_field": round(np.mean([_psnr(b, f) for b, f in zip(baked, field)]), 2),
                                  "ground_psnr": round(np.mean([_psnr(p, g) for p, g in zip(baked, gts)]), 2),
                                  "ground_lpips": _lpips(baked, gts), "load": _load()}), flush=True)


def fit(args) -> None:
    """Held-out aerial PSNR (every 4th view held out; field renderer) and ground PSNR / LPIPS
    (the preset's ground renderer) of one lane against training seconds."""
    import numpy as np
    import torch

    torch.set_num_threads(args.threads)
    # the fit is not saved: only the appearance (fit_train) is reused from --work
    ds, scene, m = _method(args, ["holdout_every=4"], Path(args.work))
    held = [f for i, f in enumerate(scene.aerial) if i % 4 == 3][:: args.aerial_stride]
    ground = _ground_frames(scene, args.per_sequence)
    gts = [f.image() for f in ground]
    floor = _mean_frame(ds)
    print(json.dumps({"lane": scene.name, "held_out_aerial": len(held), "ground_frames": len(ground),
                      "floor_ground_psnr": round(np.mean([_psnr(floor, g) for g in gts]), 2),
                      "floor_ground_lpips": _lpips([floor] * len(gts), gts)}), flush=True)

    clock = {"start": time.process_time(), "eval": 0.0}  # CPU seconds: wall time lies under load

    def callback(it, seconds, model):
        c0 = time.process_time()
        cpu = c0 - clock["start"] - clock["eval"]
        model.baked = None  # bake this state of the field (renderer="baked")
        with torch.no_grad():
            aer = np.mean([_psnr(m.render_frame(scene, f, ground=False, model=model), f.image()) for f in held])
            preds = [m.render_frame(scene, f, model=model) for f in ground]
        sig = model.baked.sigma.flatten()  # the haze a young field spreads through the box, 1/m
        model.baked = None
        clock["eval"] += time.process_time() - c0
        print(json.dumps({"iteration": it, "train_s": round(seconds, 1), "train_cpu_s": round(cpu, 1),
                          "heldout_aerial_psnr": round(aer, 2),
                          "ground_psnr": round(np.mean([_psnr(p, g) for p, g in zip(preds, gts)]), 2),
                          "ground_lpips": _lpips(preds, gts),
                          "occupied": round(float(model.grid.occupied.float().mean()), 3),
                          "sigma_median": round(float(sig.median()), 4),
                          "sigma_below_1e-3": round(float((sig < 1e-3).float().mean()), 3), "load": _load()}),
              flush=True)

    _, stats = m.fit_scene_model(scene, progress=False, callback=callback)
    print(json.dumps({k: v for k, v in stats.items() if not isinstance(v, list)}), flush=True)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("speed")
    s.add_argument("--preset", default="smoke")
    s.add_argument("--views", type=int, default=4)
    s.add_argument("--size", type=int, default=48)
    s.add_argument("--iterations", type=int, default=20)
    s.add_argument("--repeat", type=int, default=3, help="baked renders to time (they are fast)")
    s.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    s.add_argument("--set", action="append", default=[])
    for name in ("render", "fit"):
        p = sub.add_parser(name)
        screen.split_options(p)
        p.add_argument("--preset", default="small")
        p.add_argument("--set", action="append", default=[])
        p.add_argument("--lane", type=int, default=0, help="index in the validation split")
        p.add_argument("--threads", type=int, default=1)
        p.add_argument("--per-sequence", type=int, default=4, help="ground frames per sequence (8 sequences)")
        p.add_argument("--work", default=f"/tmp/bench-nerf-{name}")
    r = sub.choices["render"]
    r.add_argument("--voxels", type=float, nargs="+", default=[1.0, 0.5, 0.35])
    r.add_argument("--views", nargs="+", default=["camera", "horizontal", "aerial"])
    r.add_argument("--samples", type=int, nargs="+", default=[0], help="samples per ray (0: n_inner)")
    sub.choices["fit"].add_argument("--aerial-stride", type=int, default=2, help="every k-th held-out view")
    args = ap.parse_args(argv)
    if args.cmd != "speed":  # before anything is imported, made or read
        from skyeyes_bench.splits import screening_split

        screening_split(args.split, f"bench/nerf.py {args.cmd}")
    {"speed": speed, "render": render, "fit": fit}[args.cmd](args)


if __name__ == "__main__":
    screen.run_main(main, sys.argv[1:])
