"""3D Gaussian splatting (Kerbl et al. 2023) on a lane's aerial views, rendered from its ground
cameras: the pipeline of `gaussians3d` (vanilla) and `sugar` (its surface-aligned regularizer).

Per scene: the start is the fused MVS cloud (`reference.common.mvs_start`: dense stereo from the
aerial views, each point a disc with its own size and orientation), as 3DGS starts from an
SfM/MVS cloud; `init=sfm` uses pycolmap's sparse triangulation instead. Either falls back to
"ground-plane rays" (with a warning) when it leaves fewer than `min_init_points` in the region the
ground cameras see (+ margin). Then train (`reference.common.gaussians.train`, with the member's
`regularizer`); the Gaussians are checkpointed to `<workdir>/scenes/<scene>/model.pt`
(`Method.fit_scenes`), which a later fit on the same workdir reuses.

What is learned on the train split (`fit_train`): the colour map from aerial to ground colours
and the background colours above and below the horizon, fitted on the `mvs` reconstructions of
`train_lanes` train lanes (`reference.common.appearance`). Gaussians fitted to the aerial views
carry the aerial colours, as the `mvs` discs do, so the same map applies.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from reference.common.appearance import Appearance
from reference.common.gaussians import rasterize
from reference.common.gaussians.model import GaussianModel
from reference.common.gaussians.scene_geometry import GaussianGeometry
from reference.common.gaussians.train import TrainConfig, View, train
from reference.common.geometry import region, sfm, splat
from reference.common.mvs_cloud import learn_appearance
from reference.common.mvs_start import start_cloud
from reference.common.scene import FitConfig, held_out, region_box
from reference.method import Method
from skyeyes_bench.data.layout import Frame, Scene
from skyeyes_bench.errors import UserError


@dataclass
class Gaussians3DConfig(FitConfig, TrainConfig):
    """Training schedule (`TrainConfig`) plus the scene's and the fit's (`FitConfig`) and where
    training starts.

    Attributes:
        init: "mvs" (the fused dense cloud, `mvs_preset`'s stereo settings), "sfm" (pycolmap) or
            "plane" (the ground-plane fallback alone: an ablation, and fast tests).
        min_init_points: fewer points in the region means the ground-plane fallback init.
        init_voxel_m: the MVS cloud is merged per voxel of this side (m) before the start.
        init_disc_size: start discs' diameter in footprints.
        fallback_per_view: rays per aerial view for the fallback init.
        init_max_points: subsample the initial cloud to at most this many points.
        init_max_scale: cap of the initial (nearest-neighbour) Gaussian scale, m.
        render_near_m: (`SceneConfig`) 3 m here: Gaussians closer to a ground camera than this
            are floaters the steep aerial views cannot constrain; left in, they fog the whole
            ground view (measured on SynthTown small: ground PSNR 15.2 -> 15.7 dB at 3 m). The
            Skyeyes authors likewise remove large ellipsoids before rendering ground views.
    """

    render_near_m: float = 3.0
    init: str = "mvs"
    min_init_points: int = 500
    init_voxel_m: float = 0.5
    init_disc_size: float = 1.0
    fallback_per_view: int = 1500
    init_max_points: int = 20_000
    init_max_scale: float = 2.0


PRESETS = {
    # Seconds per scene on 2 CPU cores at 48x48 (tests, CI).
    "smoke": Gaussians3DConfig(iterations=80, densify_from=20, densify_until=60, densify_every=20,
                               sh_degree=0, max_gaussians=3000, init_max_points=1500, fallback_per_view=400,
                               opacity_reset_every=0, init_max_scale=1.0, mvs_preset="smoke", train_lanes=1),
    # The CPU default at 128x128 (about a minute and a half per lane, MVS start included).
    # 400 iterations (ground PSNR flat past them) and the `fast` MVS start keep 8 lanes within the 15-minute
    # budget; chosen on the synthtown@1/@2 test split before a validation split existed; see docs/log/runs-2026.md.
    "small": Gaussians3DConfig(iterations=400, densify_from=50, densify_until=300, densify_every=50,
                               sh_degree=1, sh_increase_every=100, max_gaussians=40_000,
                               init_max_points=30_000, opacity_reset_every=0, mvs_preset="fast"),
    # 3DGS's own schedule (GPU users; the paper trains SuGaR 15k iterations at 512x512).
    "paper": Gaussians3DConfig(iterations=15_000, densify_from=500, densify_until=7_000, densify_every=100,
                               sh_degree=3, sh_increase_every=1000, max_gaussians=1_000_000,
                               init_max_points=200_000, opacity_reset_every=3000, mvs_preset="paper",
                               init_voxel_m=0.1),
}


def frame_view(frame: Frame, *, with_image: bool = True, device: str | torch.device = "cpu") -> View:
    """The frame's image (zeros without it), pose and intrinsics as a `View` on `device`."""
    cam = frame.camera()
    img = (torch.as_tensor(frame.image(), device=device) if with_image
           else torch.zeros(frame.height, frame.width, 3, device=device))
    return View(img, torch.tensor(cam.w2c, dtype=torch.float32, device=device),
                torch.tensor(cam.K, dtype=torch.float32, device=device), name=frame.file)


class GaussianSplatting(GaussianGeometry, Method):
    """Gaussians fitted on a lane's aerial views from the MVS start, rendered from its ground
    cameras through the learned appearance; a member adds its training loss (`regularizer`).
    Without one it is vanilla 3DGS, the `gaussians3d` row and a prior a diffusion method may
    condition on (`reference.common.priors.PRIOR_PARTS`), offering its scene's geometry
    (`GaussianGeometry`: depth, points)."""

    name = "gaussians3d"
    version = "0.1"
    presets = PRESETS
    scene_checkpoint = "model.pt"

    def __init__(self, config: Gaussians3DConfig, workdir, **kw):
        super().__init__(config, workdir, **kw)
        self.appearance = Appearance()

    def regularizer(self, scene: Scene):
        """The member's extra training loss as `fn(model, iteration) -> scalar`, or None (vanilla
        3DGS)."""
        return None

    # ---------------------------------------------------------------- appearance (train split)
    def fit_train(self, dataset) -> None:
        """The colour map and backgrounds, learned from the fused MVS clouds of train lanes (`learn_appearance`)."""
        self.appearance = learn_appearance(self, dataset)

    # ---------------------------------------------------------------- fitting (a scene)
    def fit_scene_model(self, scene: Scene, *, progress: bool, callback=None) -> tuple[tuple, dict]:
        """((Gaussians, training background [3]), stats). callback(iteration, seconds, model):
        called at the training's checkpoints (bench/gaussians.py draws its curves with it)."""
        cfg = self.config
        aerial = list(scene.aerial)
        held = held_out(aerial, cfg.holdout_every)
        train_frames = [f for f in aerial if f not in held]
        box = region_box(scene, cfg)
        # 1. The start: the MVS cloud (or SfM points), else the documented fallback.
        model, msg, n_init = self._initial_model(scene, train_frames, box)
        # 2. Views with loss masks (pixels whose rays miss the region cannot be explained).
        dev = torch.device(self.device)
        model = model.to(dev)
        views = []
        for f in train_frames:
            mask = torch.as_tensor(region.rays_hit_box(f.camera(), box), device=dev)
            views.append(dataclasses.replace(frame_view(f, device=dev), mask=mask))
        # The training background stays on the CPU (saved with the checkpoint); `train` moves it.
        bg = torch.as_tensor(self.appearance.background(scene).sky, device="cpu")
        centres = np.array([f.c2w[:3, 3] for f in aerial])
        extent = max(1.1 * float(np.linalg.norm(centres - centres.mean(0), axis=1).max()), 10.0)
        # 3. Train.
        stats = train(model, views, cfg, extent=extent, box=torch.tensor(box, dtype=torch.float32, device=dev),
                      background=bg, seed=self.seed, regularizer=self.regularizer(scene), callback=callback,
                      progress=progress)
        stats.update({"init": msg, "init_points": n_init, "extent_m": extent, "box": box.tolist(),
                      "background": bg.tolist(), "held_out": [f.file for f in held]})
        return (model, bg), stats

    def save_scene_model(self, fitted: tuple, path: Path) -> None:
        model, bg = fitted
        torch.save({"params": {k: v.cpu() for k, v in model.state_dict().items()}, "background": bg,
                    "config": dataclasses.asdict(self.config)}, path)

    def load_scene_model(self, path: Path) -> tuple:
        sd = torch.load(path, weights_only=True)
        return GaussianModel.from_state_dict(sd["params"]).to(self.device), sd["background"]

    def _initial_model(self, scene: Scene, frames: list[Frame], box: np.ndarray) -> tuple[GaussianModel, str, int]:
        """The model training starts from, the log message saying where it came from, its size."""
        cfg = self.config
        log = logging.getLogger(type(self).__module__)
        rng = np.random.default_rng(self.seed)
        cloud = None
        if cfg.init == "mvs":
            cloud = start_cloud(scene, cfg, device=self.device, aerial=frames)
            cloud = splat.voxel_downsample(cloud, cfg.init_voxel_m)
            msg = f"MVS: {len(cloud)} fused points (per {cfg.init_voxel_m} m voxel) from {len(frames)} aerial views"
            if len(cloud) > cfg.init_max_points:
                cloud = cloud.subset(np.sort(rng.choice(len(cloud), cfg.init_max_points, replace=False)))
            if len(cloud) >= cfg.min_init_points:
                model = GaussianModel.from_surfels(splat.surfels(cloud, size=cfg.init_disc_size), cfg.sh_degree,
                                                   opacity=cfg.init_opacity)
                log.info("%s: init: %s", scene.name, msg)
                return model, msg, len(cloud)
            xyz, rgb = cloud.xyz.astype(np.float64), cloud.rgb
        elif cfg.init == "sfm":
            xyz, rgb, msg = sfm.sfm_points(frames, self.scene_dir(scene) / "sfm")
            keep = region.in_box(xyz, box) if len(xyz) else np.zeros(0, bool)
            xyz, rgb = xyz[keep], rgb[keep]
            msg += f"; {len(xyz)} inside the ground cameras' region"
        elif cfg.init == "plane":
            xyz, rgb, msg = np.zeros((0, 3)), np.zeros((0, 3), np.float32), "init=plane"
        else:
            raise UserError(f"gaussians3d init={cfg.init!r}: expected 'mvs', 'sfm' or 'plane'")
        if len(xyz) < cfg.min_init_points:
            fx, frgb = sfm.ground_plane_points(frames, per_view=cfg.fallback_per_view, seed=self.seed)
            keep = region.in_box(fx, box)
            xyz = np.concatenate([xyz, fx[keep]]) if len(xyz) else fx[keep]
            rgb = np.concatenate([rgb, frgb[keep]]) if len(rgb) else frgb[keep]
            msg += f"; too few (< {cfg.min_init_points}): fallback init (ground-plane rays) -> {len(xyz)} points"
            log.warning("%s: init: %s", scene.name, msg)
        else:
            log.info("%s: init: %s", scene.name, msg)
        if len(xyz) == 0:
            raise UserError(f"{scene.name}: no start point inside the region box {np.round(box, 1).tolist()} "
                            "(MVS, SfM and the ground-plane fallback found none): the aerial views do not see "
                            "the ground cameras' region")
        if len(xyz) > cfg.init_max_points:
            sel = rng.choice(len(xyz), cfg.init_max_points, replace=False)
            xyz, rgb = xyz[sel], rgb[sel]
        model = GaussianModel.from_points(xyz, rgb, cfg.sh_degree, opacity=cfg.init_opacity, seed=self.seed,
                                          max_scale=cfg.init_max_scale)
        return model, msg, len(xyz)

    # ---------------------------------------------------------------- rendering
    @torch.no_grad()
    def render_frame(self, scene: Scene, frame: Frame, *, ground: bool = True,
                     model: GaussianModel | None = None) -> np.ndarray:
        """The Gaussians over black, the learned colour map on what they cover, composited over
        the background (above / below the horizon). ground=False: as the aerial views were
        fitted (no colour map, the training background). model: instead of the scene's fitted
        one (a model in training)."""
        model = self.scene_model(scene)[0] if model is None else model
        v = frame_view(frame, with_image=False, device=model.means.device)
        out = rasterize(model.means, model.quats, model.scales, model.opacities, model.sh, v.viewmat,
                        v.K, v.width, v.height, sh_degree=self.config.sh_degree, near=self.config.render_near_m)
        alpha = out["alpha"].cpu().numpy()
        colour = (out["rgb"] / out["alpha"].clamp_min(1e-6)[..., None]).clamp(0, 1).cpu().numpy()
        if not ground:
            return splat.over(colour, alpha, np.broadcast_to(self.appearance.background(scene).sky, colour.shape))
        return self.appearance.ground_view(colour, alpha, scene, frame.camera())
