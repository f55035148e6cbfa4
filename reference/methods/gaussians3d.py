"""`gaussians3d`: vanilla 3D Gaussian splatting (Kerbl et al. 2023) fitted on a lane's aerial
views, rendered from its ground cameras. Also the shared base of `sugar`.

Per scene: SfM init (pycolmap, known poses) or the documented fallback, crop to the region the
ground cameras see (+ margin), train, checkpoint atomically to `<workdir>/scenes/<scene>/`.
A later `fit_scene` on the same workdir reuses the checkpoint (interrupted runs resume).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
import torch

from reference.common.gaussians import rasterize
from reference.common.geometry import region, sfm
from reference.common.gaussians.model import GaussianModel
from reference.common.gaussians.train import TrainConfig, View, psnr, train
from reference.method import Method
from skyeyes_bench import fileio
from skyeyes_bench.data.layout import Frame, Scene, Sequence
from skyeyes_bench.threads import set_threads

log = logging.getLogger(__name__)


@dataclass
class Gaussians3DConfig(TrainConfig):
    """Training schedule (TrainConfig) plus scene handling.

    Attributes:
        margin_m: horizontal margin around the ground cameras of the kept region (m).
        z_min, z_max: vertical extent of the kept region (world z, m).
        sfm: try pycolmap triangulation first; min_sfm_points: fewer means the fallback init.
        fallback_per_view: rays per aerial view for the fallback init.
        init_max_points: subsample the initial cloud to at most this many points.
        holdout_every: hold out every k-th aerial view from training (0: none), for curves.
        init_max_scale: cap of the initial (nearest-neighbour) Gaussian scale, m.
        render_near_m: near plane of the ground renders (m). Gaussians closer to a ground camera
            than this are floaters the steep aerial views cannot constrain; left in, they fog the
            whole ground view (measured on SynthTown small: ground PSNR 15.2 -> 15.7 dB at 3 m).
            The Skyeyes authors likewise remove large ellipsoids before rendering ground views.
        threads: torch intra-op threads. 1 by default: on a shared 2-core machine a second
            OpenMP thread made the rasterizer up to 7x slower (spin-waiting under contention).
    """

    margin_m: float = 30.0
    z_min: float = -1.0
    z_max: float = 40.0
    sfm: bool = True
    min_sfm_points: int = 500
    fallback_per_view: int = 1500
    init_max_points: int = 20_000
    holdout_every: int = 0
    init_max_scale: float = 2.0
    render_near_m: float = 3.0
    threads: int = 1


PRESETS = {
    # Seconds per scene on 2 CPU cores at 48x48 (tests, CI).
    "smoke": Gaussians3DConfig(iterations=80, densify_from=20, densify_until=60, densify_every=20,
                               sh_degree=0, max_gaussians=3000, init_max_points=1500, fallback_per_view=400,
                               opacity_reset_every=0, init_max_scale=1.0),
    # The CPU default at 128x128 (minutes per scene).
    "small": Gaussians3DConfig(iterations=400, densify_from=50, densify_until=300, densify_every=50,
                               sh_degree=1, sh_increase_every=200, max_gaussians=15_000,
                               init_max_points=8_000, opacity_reset_every=0),
    # 3DGS's own schedule (GPU users; the paper trains SuGaR 15k iterations at 512x512).
    "paper": Gaussians3DConfig(iterations=15_000, densify_from=500, densify_until=7_000, densify_every=100,
                               sh_degree=3, sh_increase_every=1000, max_gaussians=1_000_000,
                               init_max_points=200_000, opacity_reset_every=3000),
}


def frame_view(frame: Frame, *, with_image: bool = True) -> View:
    cam = frame.camera()
    img = torch.from_numpy(frame.image()) if with_image else torch.zeros(frame.height, frame.width, 3)
    return View(img, torch.tensor(cam.w2c, dtype=torch.float32), torch.tensor(cam.K, dtype=torch.float32),
                name=frame.file)


def rays_hit_box(frame: Frame, box: np.ndarray) -> np.ndarray:
    """[H, W] bool: the pixel's ray crosses the box (else no Gaussian of ours can explain it)."""
    cam = frame.camera()
    h, w = frame.height, frame.width
    v, u = np.mgrid[0:h, 0:w] + 0.5
    d = np.stack([(u - cam.K[0, 2]) / cam.K[0, 0], (v - cam.K[1, 2]) / cam.K[1, 1], np.ones_like(u)], -1)
    d = d @ cam.c2w[:3, :3].T
    o = cam.c2w[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (box[0] - o) / d
        t1 = (box[1] - o) / d
    tmin = np.nanmax(np.minimum(t0, t1), -1)
    tmax = np.nanmin(np.maximum(t0, t1), -1)
    return (tmax >= np.maximum(tmin, 0)) & (tmax > 0)


def sky_colour(frames: list[Frame]) -> np.ndarray:
    """Mean colour [3] of aerial pixels whose ray points above the horizon (grey if none)."""
    acc, n = np.zeros(3), 0
    for f in frames:
        cam = f.camera()
        v = np.arange(f.height) + 0.5
        dz = (v - cam.K[1, 2]) / cam.K[1, 1] * cam.c2w[2, 1] + cam.c2w[2, 2]  # ray z at image centre column
        rows = dz > 0.05
        if rows.any():
            acc += f.image()[rows].reshape(-1, 3).sum(0)
            n += int(rows.sum()) * f.width
    return (acc / n).astype(np.float32) if n else np.full(3, 0.5, np.float32)


class Gaussians3D(Method):
    name = "gaussians3d"
    version = "0.1"
    presets = PRESETS

    def __init__(self, config, workdir, *, seed: int = 0):
        super().__init__(config, workdir, seed=seed)
        self._models: dict[str, tuple[GaussianModel, torch.Tensor]] = {}
        self.scene_stats: dict[str, dict] = {}

    # ---------------------------------------------------------------- hooks for subclasses
    def regularizer(self, scene: Scene):
        """Extra training loss as `fn(model, iteration) -> scalar`, or None (vanilla 3DGS)."""
        return None

    # ---------------------------------------------------------------- fitting
    def scene_dir(self, scene: Scene) -> Path:
        return self.workdir / "scenes" / scene.name

    def fit_scene(self, scene: Scene, *, callback=None, progress: bool = True) -> None:
        cfg = self.config
        set_threads(cfg.threads)
        ckpt = self.scene_dir(scene) / "model.pt"
        if ckpt.is_file():
            self._load(scene)
            log.info("%s: reusing fitted model %s", scene.name, ckpt)
            return
        t0 = time.perf_counter()
        aerial = list(scene.aerial)
        held = [f for i, f in enumerate(aerial) if cfg.holdout_every and i % cfg.holdout_every == cfg.holdout_every - 1]
        train_frames = [f for f in aerial if f not in held]
        box = region.region_box(list(scene.ground), cfg.margin_m, (cfg.z_min, cfg.z_max))
        # 1. Initial points: SfM with the known poses, else the documented fallback.
        msg = "SfM disabled by config"
        xyz, rgb = np.zeros((0, 3)), np.zeros((0, 3), np.float32)
        if cfg.sfm:
            xyz, rgb, msg = sfm.sfm_points(train_frames, self.scene_dir(scene) / "sfm")
            keep = region.in_box(xyz, box) if len(xyz) else np.zeros(0, bool)
            xyz, rgb = xyz[keep], rgb[keep]
            msg += f"; {len(xyz)} inside the ground cameras' region"
        if len(xyz) < cfg.min_sfm_points:
            fx, frgb = sfm.ground_plane_points(train_frames, per_view=cfg.fallback_per_view, seed=self.seed)
            keep = region.in_box(fx, box)
            xyz = np.concatenate([xyz, fx[keep]]) if len(xyz) else fx[keep]
            rgb = np.concatenate([rgb, frgb[keep]]) if len(rgb) else frgb[keep]
            msg += f"; too few (< {cfg.min_sfm_points}): fallback init (ground-plane rays) -> {len(xyz)} points"
        log.warning("%s: init: %s", scene.name, msg) if "fallback" in msg else log.info("%s: init: %s", scene.name, msg)
        rng = np.random.default_rng(self.seed)
        if len(xyz) > cfg.init_max_points:
            sel = rng.choice(len(xyz), cfg.init_max_points, replace=False)
            xyz, rgb = xyz[sel], rgb[sel]
        model = GaussianModel.from_points(xyz, rgb, cfg.sh_degree, opacity=cfg.init_opacity, seed=self.seed,
                                          max_scale=cfg.init_max_scale)
        # 2. Views with loss masks (pixels whose rays miss the region cannot be explained).
        views = []
        for f in train_frames:
            v = frame_view(f)
            v.mask = torch.from_numpy(rays_hit_box(f, box))
            views.append(v)
        bg = torch.from_numpy(sky_colour(aerial))
        centres = np.array([f.c2w[:3, 3] for f in aerial])
        extent = max(1.1 * float(np.linalg.norm(centres - centres.mean(0), axis=1).max()), 10.0)
        # 3. Train.
        stats = train(model, views, cfg, extent=extent, box=torch.tensor(box, dtype=torch.float32), background=bg,
                      seed=self.seed, regularizer=self.regularizer(scene), callback=callback, progress=progress)
        stats.update({"init": msg, "init_points": int(len(xyz)), "extent_m": extent, "box": box.tolist(),
                      "background": bg.tolist(), "fit_seconds": time.perf_counter() - t0,
                      "held_out": [f.file for f in held]})
        # 4. Checkpoint atomically (a killed run leaves no half file; the next run refits).
        self.scene_dir(scene).mkdir(parents=True, exist_ok=True)
        with fileio.atomic_path(ckpt) as tmp:
            torch.save({"params": model.state_dict(), "background": bg, "config": dataclasses.asdict(cfg)}, tmp)
        fileio.write_json(self.scene_dir(scene) / "fit.json", stats)
        self._models[scene.name] = (model, bg)
        self.scene_stats[scene.name] = stats

    def _load(self, scene: Scene) -> tuple[GaussianModel, torch.Tensor]:
        if scene.name not in self._models:
            ckpt = self.scene_dir(scene) / "model.pt"
            if not ckpt.is_file():
                raise RuntimeError(f"{scene.name}: render before fit_scene (no {ckpt})")
            sd = torch.load(ckpt, weights_only=True)
            self._models[scene.name] = (GaussianModel.from_state_dict(sd["params"]), sd["background"])
            fit = self.scene_dir(scene) / "fit.json"
            if fit.is_file():
                self.scene_stats[scene.name] = json.loads(fit.read_text())
        return self._models[scene.name]

    # ---------------------------------------------------------------- rendering
    @torch.no_grad()
    def render_frame(self, scene: Scene, frame: Frame) -> np.ndarray:
        model, bg = self._load(scene)
        v = frame_view(frame, with_image=False)
        out = rasterize(model.means, model.quats, model.scales, model.opacities, model.sh, v.viewmat, v.K,
                        v.width, v.height, background=bg, sh_degree=self.config.sh_degree,
                        near=self.config.render_near_m)
        return out["rgb"].clamp(0, 1).numpy().astype(np.float32)

    def render_sequence(self, scene: Scene, sequence: Sequence) -> Iterator[np.ndarray]:
        set_threads(self.config.threads)
        for frame in sequence:
            yield self.render_frame(scene, frame)


# --------------------------------------------------------------------------- bench helper


def fit_curve(preset: str, method: str = "gaussians3d", *, data: str | None = None, seconds: float | None = None,
              workdir: str | None = None, overrides: dict | None = None) -> list[dict]:
    """Held-out aerial PSNR and ground-view PSNR against training seconds, for the first test
    scene of a SynthTown preset (bench/gaussians.py). Prints one line per checkpoint."""
    import tempfile

    from reference.methods import get_method_class
    from skyeyes_bench.data.layout import open_dataset

    if data is None:
        from skyeyes_bench.data.synthtown import ensure_dataset

        data = ensure_dataset(preset if preset in ("smoke", "small", "paper") else "small")
    ds = open_dataset(data)
    scene = ds.split("test")[0]
    cls = get_method_class(method)
    wd = Path(workdir or tempfile.mkdtemp(prefix="gs-curve-"))
    m = cls.from_preset(preset, wd, holdout_every=8, **(overrides or {}))
    aerial = list(scene.aerial)
    held = [f for i, f in enumerate(aerial) if i % 8 == 7]
    ground = [f for s in scene.sequences.values() for f in s.frames[::4]]
    rows: list[dict] = []
    print(f"scene {scene.name}: {len(aerial) - len(held)} train / {len(held)} held-out aerial views, "
          f"{len(ground)} ground frames scored; method {method}, preset {preset}")
    print(f"{'iter':>6} {'train s':>8} {'gaussians':>9} {'aerial PSNR':>11} {'ground PSNR':>11}")

    def cb(it, secs, model):
        if seconds is not None and secs > seconds:
            return
        m._models[scene.name] = (model, torch.from_numpy(sky_colour(aerial)))
        with torch.no_grad():
            pa = np.mean([psnr(torch.from_numpy(m.render_frame(scene, f)), torch.from_numpy(f.image())) for f in held])
            pg = np.mean([psnr(torch.from_numpy(m.render_frame(scene, f)), torch.from_numpy(f.image())) for f in ground])
        rows.append({"iteration": it, "train_s": secs, "gaussians": len(model), "aerial_psnr": pa, "ground_psnr": pg})
        print(f"{it:>6} {secs:>8.1f} {len(model):>9} {pa:>11.2f} {pg:>11.2f}", flush=True)

    m.fit_scene(scene, callback=cb, progress=False)
    return rows
