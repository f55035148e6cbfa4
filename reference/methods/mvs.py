"""`mvs`: the paper's MVS row (Schoenberger et al. 2016). Dense depth for every aerial view of a
lane from its neighbours (plane sweep with NCC, semi-global aggregation), kept where other
views agree (geometric consistency), fused into one coloured cloud of the region the ground
cameras see, and drawn into each ground camera as surface discs sized by each point's footprint
(`reference.common.geometry`). Pixels no disc covers show the background; nothing is invented.

What the method learns on the train split (`fit_train`, `train_lanes` of them): the same
reconstruction of each train lane rendered into its ground cameras gives (render, truth) pairs,
from which it fits a global colour map (aerial haze -> ground colours) and the two background
colours (`reference.common.appearance`). `train_lanes=0` turns that off: backgrounds then come
from the test lane alone (sky: aerial pixels above the horizon; ground: the cloud's lowest
layer).

Per scene the fused cloud is checkpointed atomically to `<workdir>/scenes/<scene>/cloud.npz`
with `fit.json`; a later run on the same workdir reuses it.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import Iterator

import numpy as np
import torch

from reference.common.appearance import AppearanceFit, Backgrounds, ColourMap
from reference.common.geometry import mvs as gmvs
from reference.common.geometry import region, splat
from reference.method import Method
from skyeyes_bench import fileio
from skyeyes_bench.data.layout import Dataset, Scene, Sequence
from skyeyes_bench.threads import set_threads

log = logging.getLogger(__name__)


@dataclass
class MVSMethodConfig(gmvs.MVSConfig):
    """Stereo settings (`MVSConfig`) plus region, rendering and what is learned on the train split.

    Attributes:
        margin_m, z_min, z_max: the region around the ground cameras (as `gaussians3d`).
        voxel_m: fused points are merged per voxel of this side (m) before rendering; 0 keeps all.
        max_stretch: cap of a footprint's 1 / cos(viewing angle) growth (1: the pixel's size
            across the ray only; grazing surfaces then leave gaps other views fill).
        disc_size: disc diameter in footprints.
        opacity: disc opacity (near 1: a z-buffer; lower blends the nearest surfaces).
        ground_snap_m: fused points within this height (m) of the street (`ground_height`) are
            put on it, points farther below it dropped; 0 turns the prior off. The stereo puts the
            street up to ~1 m off its height (SynthTown small: fused street points spread over
            -1..+1.5 m), which a ground camera 2 m above it sees as clutter smeared towards the
            horizon. 2 m also flattens cars (measured on lane 0, 40 frames, PSNR after the colour
            map: off 16.05, 0.5 m 16.07, 1 m 16.17, 1.5 m 16.32, 2 m 16.39, 3 m 16.46).
        render_near_m: discs nearer to a ground camera than this are not drawn.
        train_lanes: train lanes reconstructed to learn the colour map and backgrounds (0: none).
        device: torch device of the plane sweep and the renderer ("cpu", "cuda", ...).
        threads: torch intra-op threads on the CPU. 1 by default, as `gaussians3d`: on this shared
            2-core machine a second OpenMP thread made a smoke run 95 s instead of 14 s, and under
            load 4-5 a small lane's stereo 170 s instead of 156 s.
    """

    margin_m: float = 30.0
    z_min: float = -1.0
    z_max: float = 40.0
    voxel_m: float = 0.25
    max_stretch: float = 1.0
    disc_size: float = 1.0
    opacity: float = 0.98
    ground_snap_m: float = 2.0
    render_near_m: float = 0.5
    train_lanes: int = 2
    device: str = "cpu"
    threads: int = 1


PRESETS = {
    # Seconds at 48x48 (tests, CI).
    "smoke": MVSMethodConfig(planes=32, num_sources=4, train_lanes=1, min_consistent=1),
    # The CPU default at 128x128 (about half a minute per lane).
    "small": MVSMethodConfig(),
    # GPU users at 512x512: more planes and sources, every train lane.
    "paper": MVSMethodConfig(planes=256, num_sources=8, window=7, train_lanes=1000, voxel_m=0.1),
}


def reconstruct(scene: Scene, cfg: MVSMethodConfig, *, aerial: list | None = None,
                progress: bool = False) -> tuple[gmvs.PointCloud, dict]:
    """Fused cloud of one lane (cropped to its region box) and the stereo stats; `aerial`: the
    views to use (default all of the scene's)."""
    aerial = list(scene.aerial) if aerial is None else aerial
    box = region.region_box(list(scene.ground), cfg.margin_m, (cfg.z_min, cfg.z_max))
    stereo = gmvs.MVSConfig(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(gmvs.MVSConfig)})
    cloud, _, stats = gmvs.run_mvs([f.image() for f in aerial], [f.camera() for f in aerial], box, stereo,
                                   device=cfg.device, progress=progress, max_stretch=cfg.max_stretch)
    stats["box"] = box.tolist()
    z0 = gmvs.ground_height(cloud)
    stats["street_height_m"] = z0
    if z0 is not None and cfg.ground_snap_m > 0:
        cloud = gmvs.snap_to_plane(cloud, (np.array([0.0, 0.0, 1.0]), z0), cfg.ground_snap_m)
    stats["points"] = len(cloud)
    return cloud, stats


class MVS(Method):
    name = "mvs"
    version = "0.1"
    presets = PRESETS

    def __init__(self, config, workdir, *, seed: int = 0):
        super().__init__(config, workdir, seed=seed)
        self._surfels: dict[str, tuple[dict, np.ndarray | None]] = {}
        self.scene_stats: dict[str, dict] = {}
        self.colour_map = ColourMap()
        self.backgrounds: Backgrounds | None = None

    # ---------------------------------------------------------------- train split
    def fit_train(self, dataset: Dataset) -> None:
        cfg = self.config
        path = self.workdir / "train" / "appearance.json"
        if path.is_file():
            d = fileio.read_json(path, allow_nan=True)
            self.colour_map = ColourMap.from_dict(d["colour_map"])
            self.backgrounds = Backgrounds.from_dict(d["backgrounds"]) if d.get("backgrounds") else None
            log.info("appearance: reusing %s", path)
            return
        lanes = dataset.split("train")[: max(cfg.train_lanes, 0)]
        if not lanes:
            log.info("appearance: no train lanes used (train_lanes=%d): identity colour map", cfg.train_lanes)
            return
        set_threads(cfg.threads)
        t0 = time.perf_counter()
        acc = AppearanceFit(seed=self.seed)
        grey = np.full(3, 0.5, np.float32)
        for lane in lanes:
            cloud, _ = reconstruct(lane, cfg)
            params = self._surfel_params(cloud)
            for seq in lane.sequences.values():
                for f in seq:
                    cam = f.camera()
                    rgb, alpha = splat.render_cloud(params, cam, opacity=cfg.opacity, near=cfg.render_near_m,
                                                    device=cfg.device)
                    acc.add(rgb, alpha, f.image(), cam)
        self.colour_map, self.backgrounds = acc.result(grey, grey)
        info = {"colour_map": self.colour_map.to_dict(), "backgrounds": self.backgrounds.to_dict(),
                "train_lanes": [lane.name for lane in lanes], "seconds": time.perf_counter() - t0}
        fileio.write_json(path, info)
        log.info("appearance: fitted on %d train lanes in %.0f s (sky %s, ground %s)", len(lanes), info["seconds"],
                 np.round(self.backgrounds.sky, 3).tolist(), np.round(self.backgrounds.ground, 3).tolist())

    # ---------------------------------------------------------------- test scenes
    def _surfel_params(self, cloud: gmvs.PointCloud) -> dict:
        cfg = self.config
        params = splat.surfels(splat.voxel_downsample(cloud, cfg.voxel_m), size=cfg.disc_size)
        return {k: v.to(cfg.device) for k, v in params.items()}

    def fit_scene(self, scene: Scene, *, progress: bool = True) -> None:
        cfg = self.config
        set_threads(cfg.threads)
        if self.resume_scene(scene, "cloud.npz", self._load):
            return
        t0 = time.perf_counter()
        cloud, stats = reconstruct(scene, cfg, progress=progress)
        if len(cloud) == 0:
            log.warning("%s: MVS fused no point (%s): every ground frame will be the background", scene.name, stats)
        stats["fit_seconds"] = time.perf_counter() - t0
        self.scene_dir(scene).mkdir(parents=True, exist_ok=True)
        with fileio.atomic_path(self.scene_dir(scene) / "cloud.npz") as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, **dataclasses.asdict(cloud))
        fileio.write_json(self.scene_dir(scene) / "fit.json", stats)
        self.scene_stats[scene.name] = stats
        self._surfels[scene.name] = (self._surfel_params(cloud), splat.ground_colour(cloud))
        log.info("%s: %d fused points (coverage %.2f raw, %.2f consistent) in %.0f s", scene.name, len(cloud),
                 stats["raw_coverage"], stats["filtered_coverage"], stats["fit_seconds"])

    def _load(self, scene: Scene) -> tuple[dict, np.ndarray | None]:
        if scene.name not in self._surfels:
            ckpt = self.scene_dir(scene) / "cloud.npz"
            if not ckpt.is_file():
                raise RuntimeError(f"{scene.name}: render before fit_scene (no {ckpt})")
            with np.load(ckpt) as z:
                cloud = gmvs.PointCloud(**{k: z[k] for k in ("xyz", "rgb", "normals", "footprint")})
            self._surfels[scene.name] = (self._surfel_params(cloud), splat.ground_colour(cloud))
            fit = self.scene_dir(scene) / "fit.json"
            if fit.is_file():
                self.scene_stats[scene.name] = fileio.read_json(fit, allow_nan=True)
        return self._surfels[scene.name]

    def _backgrounds(self, scene: Scene, ground: np.ndarray | None) -> Backgrounds:
        if self.backgrounds is not None:
            return self.backgrounds
        from reference.methods.gaussians3d import sky_colour

        sky = sky_colour(list(scene.aerial))
        return Backgrounds(sky, ground if ground is not None else sky)

    @torch.no_grad()
    def render_sequence(self, scene: Scene, sequence: Sequence) -> Iterator[np.ndarray]:
        cfg = self.config
        set_threads(cfg.threads)
        params, ground = self._load(scene)
        bgs = self._backgrounds(scene, ground)
        for frame in sequence:
            cam = frame.camera()
            rgb, alpha = splat.render_cloud(params, cam, opacity=cfg.opacity, near=cfg.render_near_m,
                                            device=cfg.device)
            # The colour map corrects what the aerial views saw; the background is already a
            # ground-view colour.
            yield splat.over(self.colour_map(rgb), alpha, bgs.image(cam))
