"""`nerf`: the paper's NeRF row, a compact Instant-NGP (Müller et al. 2022) fitted on a lane's
aerial views, rendered from its ground cameras (`reference.common.nerf`).

Per scene: the scene box is the region the ground cameras see (`region.region_box`), mapped to
[-1, 1]^3; everything beyond is contracted into the shell up to [-2, 2]^3 (mip-NeRF 360), so the
distant town seen by the aerial views has a place. With `init=mvs` the fused cloud of the `mvs`
method (dense stereo from the same aerial views) marks the occupancy grid's cells and the density
is pulled towards it for `init_steps` steps before the photometric fit; `init=none` starts from an
empty field and Instant-NGP's warm-up of the grid. The field and grid are checkpointed to
`<workdir>/scenes/<scene>/model.pt` (`Method.fit_scenes`).

Ground renders: the field over black, the colour map learned on the train split (as `mvs` and
`gaussians3d`, `reference.common.appearance`: aerial haze -> ground colours) on what it covers, over the background above / below
the horizon. No aerial view sees the sky the ground cameras look at, so the NeRF cannot know it.
With `renderer="baked"` (the default) the fit ends by baking the field on a grid over the box
(`reference.common.nerf.bake`; colour seen from the nearest ground camera), and the ground frames
are rendered from that grid: the field renderer evaluates the hash grid and MLP at every sample
of every ground ray (nothing is pruned), ~2.5k rays/s on one thread, hours for a `small` split.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from reference.common.appearance import Appearance
from reference.common.mvs_cloud import learn_appearance
from reference.common.geometry import splat
from reference.common.mvs_start import start_cloud
from reference.common.nerf import BakedField, Model, NeRFConfig, NeRFField, OccupancyGrid, SceneBox, bake_field
from reference.common.nerf import camera_rays, pretrain_density, render_baked_camera, render_camera, train
from reference.common.nerf.bake import VIEWS
from reference.common.nerf.render import to_unit
from reference.common.scene import FitConfig, held_out, region_box
from reference.method import Method
from skyeyes_bench.data.layout import Frame, Scene
from skyeyes_bench.errors import UserError

log = logging.getLogger(__name__)


@dataclass
class NeRFMethodConfig(FitConfig, NeRFConfig):
    """The NeRF (`NeRFConfig`) plus the scene's and the fit's (`FitConfig`: the box around the
    ground cameras, train lanes, device, threads, stereo preset, held-out views) and where the
    field starts.

    Attributes:
        init: "none" (an empty field, Instant-NGP's grid warm-up) or "mvs" (occupancy and density
            start from the fused cloud of `mvs_preset`). "none" by default: measured on the smoke
            lane (150 iterations), the MVS start trains 2.2x faster (28 instead of 64 evaluated
            samples per ray) and reaches a higher held-out aerial PSNR (18.0 against 17.2 dB), but
            the dense layer it grows around the street is where the ground cameras stand: their
            views are fog (opacity 1.00, ground PSNR 8-12 dB against 14.6-16.2 from "none").
        init_steps: density steps towards the cloud before the photometric fit.
        init_dilate: occupancy cells around each cloud point also marked occupied.
        render_near_m: (`SceneConfig`) 1 m here: ground renders start this far from the camera:
            floaters near a ground camera are where the steep aerial views constrain nothing.
        ground_far_field: ground renders include the contracted far field. Off by default: the
            aerial views never look up or along the street to the horizon, so the far field the
            ground cameras look through there is untrained (opaque: a fresh field's small density
            over kilometres; measured on the smoke lane: opacity 1.00 in every ground pixel and
            ground PSNR 8-12 dB); the learned backgrounds stand in for it, as for `gaussians3d`.
        renderer: "baked" (ground frames from the field baked on a grid over the box, at the end
            of the fit) or "field" (the field at every sample: the reference, ~50x slower).
        bake_voxel_m: the baked grid's largest vertex spacing (m).
        bake_view: the baked colour's view direction: "camera" (from the nearest ground camera
            centre to the vertex), "horizontal" or "aerial" (the mean over 8 directions level or
            45 deg down; `reference.common.nerf.bake`).
        bake_samples: samples per ground ray through the baked box (0: n_inner, the field
            renderer's).
    """

    render_near_m: float = 1.0
    init: str = "none"
    init_steps: int = 100
    init_dilate: int = 1
    ground_far_field: bool = False
    renderer: str = "baked"
    bake_voxel_m: float = 0.5
    bake_view: str = "camera"
    bake_samples: int = 0


PRESETS = {
    # Seconds per scene at 48x48 (tests, CI).
    "smoke": NeRFMethodConfig(iterations=150, batch_rays=1024, levels=6, log2_T=14, n_max=256, hidden=32,
                              n_inner=64, n_outer=16, occ_res=32, occ_warmup=32, init_steps=40, mvs_preset="smoke",
                              train_lanes=1, bake_voxel_m=1.0),
    # The CPU default at 128x128 (docs/reproduce.md, "Method `nerf`": measured on test-0-lane00).
    # 32 + 16 samples per ray: half the cost of 64 + 16 at the same held-out aerial and ground
    # PSNR after 100 steps (21.83 / 15.93 against 21.64 / 16.01 dB). 400 steps: ground PSNR rose
    # from 16.01 (100 steps) to 16.57 (300, at 64 samples) and still rises; ~0.25 CPU-s a step,
    # so 8 lanes on 2 workers plus the renders fit 15 minutes on a free machine. A 1 m bake
    # renders what the field renders (47 dB apart, ground PSNR 16.04 against 16.02), 0.5 m costs
    # 10x the bake seconds for 49.6 dB.
    "small": NeRFMethodConfig(iterations=400, batch_rays=1024, hidden=32, n_inner=32, n_outer=16, occ_res=48,
                              occ_warmup=32, mvs_preset="fast", bake_voxel_m=1.0),
    # Instant-NGP's own scale (GPU users, 512x512): the field renders the ground frames itself
    # (a bake at 0.5 m would be coarser than its 4096-cell finest level).
    "paper": NeRFMethodConfig(iterations=20_000, batch_rays=8192, levels=16, log2_T=19, n_max=4096, n_inner=256,
                              n_outer=64, occ_res=128, occ_warmup=256, init_steps=500, mvs_preset="paper",
                              chunk=16384, renderer="field"),
}


class NeRF(Method):
    """The field on the aerial views; the appearance learned on the train split as `gaussians3d`'s
    (`reference.common.mvs_cloud.learn_appearance`)."""

    name = "nerf"
    version = "0.1"
    kind = "baseline"
    presets = PRESETS
    scene_checkpoint = "model.pt"

    def components(self) -> list[str]:
        return ["Instant-NGP field fitted on the lane's aerial views", "rendered at the ground cameras", "colours mapped as learned on the train split"]

    def __init__(self, config: NeRFMethodConfig, workdir, **kw):
        super().__init__(config, workdir, **kw)
        self.appearance = Appearance()

    def fit_train(self, dataset) -> None:
        """The colour map and backgrounds, learned from the fused MVS clouds of train lanes (`learn_appearance`)."""
        self.appearance = learn_appearance(self, dataset)

    def _box(self, scene: Scene) -> SceneBox:
        box = region_box(scene, self.config)
        return SceneBox(box[0], box[1])

    def _new_model(self, scene: Scene) -> Model:
        cfg, dev = self.config, torch.device(self.device)
        box = self._box(scene)
        fld = NeRFField(cfg.field_config(), seed=self.seed).to(dev)
        grid = OccupancyGrid(cfg.occ_res, step_m=cfg.inner_step(box), alpha=cfg.occ_alpha,
                             mean_clamp=cfg.occ_mean_clamp, device=dev)
        bg = torch.tensor(self.appearance.background(scene).sky, dtype=torch.float32, device=dev)
        return Model(fld, grid, box, bg)

    def fit_scene_model(self, scene: Scene, *, progress: bool, callback=None) -> tuple[Model, dict]:
        """(the fitted model, stats). callback(iteration, seconds, model): every 100 steps
        (bench/nerf.py draws its curves with it)."""
        cfg = self.config
        aerial = list(scene.aerial)
        held = held_out(aerial, cfg.holdout_every)
        frames = [f for f in aerial if f not in held]
        model = self._new_model(scene)
        # 1. The start: empty, or the MVS cloud in the occupancy grid and the density.
        stats: dict = {"init": cfg.init, "held_out": [f.file for f in held]}
        if cfg.renderer not in ("baked", "field"):
            raise UserError(f"nerf renderer={cfg.renderer!r}: expected 'baked' or 'field'")
        if cfg.bake_view not in VIEWS:
            raise UserError(f"nerf bake_view={cfg.bake_view!r}: expected one of {', '.join(VIEWS)}")
        if cfg.init == "mvs":
            stats.update(self._mvs_start(scene, model, frames))
        elif cfg.init != "none":
            raise UserError(f"nerf init={cfg.init!r}: expected 'mvs' or 'none'")
        # 2. Train on every pixel of the training aerial views.
        rays = camera_rays([f.camera() for f in frames], [f.image() for f in frames], model.background.device)
        stats.update(train(model, rays, cfg, seed=self.seed, full_warmup=stats.get("init_points", 0) == 0,
                           progress=progress, callback=callback))
        stats["box"] = [model.box.lo.tolist(), model.box.hi.tolist()]
        log.info("%s: %d iterations in %.0f s (%.0f rays/s), loss %.4f, occupied %.2f", scene.name, cfg.iterations,
                 stats["train_seconds"], stats["train_rays_per_s"], stats["final_loss"], stats["occupied_fraction"])
        # 3. Bake the field for the ground renders (in the fit: the fits run in parallel, the renders do not).
        if cfg.renderer == "baked":
            import time

            t0 = time.perf_counter()
            model.baked = self._bake(scene, model)
            stats.update({"bake_seconds": time.perf_counter() - t0, "bake_shape": list(model.baked.shape)})
            log.info("%s: baked %s vertices in %.1f s", scene.name, "x".join(map(str, model.baked.shape)),
                     stats["bake_seconds"])
        return model, stats

    def _bake(self, scene: Scene, model: Model) -> BakedField:
        cfg = self.config
        centres = torch.tensor(np.unique(np.array([f.c2w[:3, 3] for f in scene.ground]), axis=0),
                               dtype=torch.float32, device=model.background.device)
        return bake_field(model.field, model.box, voxel_m=cfg.bake_voxel_m, view=cfg.bake_view, centres=centres,
                          grid=model.grid)

    def _mvs_start(self, scene: Scene, model: Model, frames: list[Frame]) -> dict:
        import time

        cfg = self.config
        t0 = time.perf_counter()
        cloud = start_cloud(scene, cfg, device=self.device, aerial=frames)
        t_mvs = time.perf_counter() - t0
        if len(cloud) == 0:
            log.warning("%s: init: MVS fused no point: starting from an empty field", scene.name)
            return {"init_points": 0, "mvs_seconds": t_mvs}
        pts = torch.tensor(cloud.xyz, dtype=torch.float32, device=model.background.device)
        model.grid.mark_points(to_unit(model.box.normalise(pts)), dilate=cfg.init_dilate)
        occ0 = float(model.grid.occupied.float().mean())
        loss = pretrain_density(model, pts, cfg, steps=cfg.init_steps, seed=self.seed)
        log.info("%s: init: %d MVS points, %.2f of the grid occupied, density loss %.3f", scene.name, len(cloud), occ0,
                 loss)
        return {"init_points": len(cloud), "init_occupied": occ0, "init_loss": loss, "mvs_seconds": t_mvs,
                "init_seconds": time.perf_counter() - t0}

    def save_scene_model(self, model: Model, path: Path) -> None:
        torch.save({"field": {k: v.cpu() for k, v in model.field.state_dict().items()},
                    "grid": model.grid.state_dict(), "box": [model.box.lo.tolist(), model.box.hi.tolist()],
                    "background": model.background.cpu(), "config": dataclasses.asdict(self.config),
                    "baked": None if model.baked is None else model.baked.state_dict()}, path)

    def load_scene_model(self, path: Path) -> Model:
        sd = torch.load(path, weights_only=True)
        dev = torch.device(self.device)
        box = SceneBox(np.array(sd["box"][0]), np.array(sd["box"][1]))
        fld = NeRFField(self.config.field_config(), seed=self.seed)
        fld.load_state_dict(sd["field"])
        grid = OccupancyGrid(sd["grid"]["res"], step_m=self.config.inner_step(box), alpha=sd["grid"]["alpha"],
                             decay=sd["grid"]["decay"], mean_clamp=sd["grid"].get("mean_clamp", False), device=dev)
        grid.load(sd["grid"])
        baked = None if sd.get("baked") is None else BakedField.from_state_dict(sd["baked"], dev)
        return Model(fld.to(dev), grid, box, sd["background"].to(dev), baked)

    # ---------------------------------------------------------------- rendering
    def render_frame(self, scene: Scene, frame: Frame, *, ground: bool = True,
                     model: Model | None = None) -> np.ndarray:
        """As `gaussians3d.render_frame`: ground=False renders as the aerial views were fitted."""
        cfg = self.config
        model = self.scene_model(scene) if model is None else model
        cam = frame.camera()
        near = cfg.render_near_m if ground else cfg.near_m
        if ground and cfg.renderer == "baked" and not cfg.ground_far_field:
            if model.baked is None:  # a model in training (bench/nerf.py's curves)
                model.baked = self._bake(scene, model)
            rgb, alpha = render_baked_camera(model.baked, cam, n_samples=cfg.bake_samples or cfg.n_inner, near=near,
                                             colour_eps=cfg.colour_eps)
        else:
            rgb, alpha = render_camera(model, cam, cfg, near=near, far_field=cfg.ground_far_field or not ground)
        colour = np.clip(rgb / np.maximum(alpha, 1e-6)[..., None], 0, 1)
        if not ground:
            return splat.over(colour, alpha, np.broadcast_to(model.background.cpu().numpy(), colour.shape))
        return self.appearance.ground_view(colour, alpha, scene, cam)
