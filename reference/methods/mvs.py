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

Checkpoints (`Method.checkpointed`): the appearance in `<workdir>/train/appearance.json`, each
scene's fused cloud in `<workdir>/scenes/<scene>/cloud.npz`, each with its `fit.json`; a later
run on the same workdir reuses them.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
import torch

from reference.common.appearance import AppearanceFit, Backgrounds, ColourMap, sky_colour
from reference.common.geometry import mvs as gmvs
from reference.common.geometry import region, splat
from reference.common.geometry.cloud import PointCloud, ground_height, snap_to_plane, street_ceiling
from reference.method import Method
from skyeyes_bench import fileio
from skyeyes_bench.data.layout import Dataset, Scene, Sequence

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
    # The CPU default at 128x128: 141 CPU-s per synthtown@2 lane (64 aerial views; bench/mvs.py,
    # test-0-lane00, load 5.6, 2026-11-25).
    "small": MVSMethodConfig(),
    # The start of the splatting methods and their appearance at `small`: half the cost for the
    # same depth accuracy, fewer points (bench/mvs.py, synthtown@2 test-0-lane00, load 5.6-5.9:
    # 70 against 141 CPU-s; within 0.5 m 0.48 and 0.48, within 2% 0.61 and 0.61, completeness
    # 0.27 against 0.43; planes=48 as well: 52 CPU-s, 0.45 / 0.58 / 0.23).
    "fast": MVSMethodConfig(planes=64, num_sources=4),
    # GPU users at 512x512: more planes and sources, every train lane.
    "paper": MVSMethodConfig(planes=256, num_sources=8, window=7, train_lanes=1000, voxel_m=0.1),
}


def reconstruct(scene: Scene, cfg: MVSMethodConfig, *, device: str, aerial: list | None = None,
                progress: bool = False) -> tuple[PointCloud, dict]:
    """Fused cloud of one lane (cropped to its region box) on `device`, and the stereo stats;
    `aerial`: the views to use (default all of the scene's)."""
    aerial = list(scene.aerial) if aerial is None else aerial
    box = region.region_box(list(scene.ground), cfg.margin_m, (cfg.z_min, cfg.z_max))
    stereo = gmvs.MVSConfig(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(gmvs.MVSConfig)})
    cloud, _, stats = gmvs.run_mvs([f.image() for f in aerial], [f.camera() for f in aerial], box, stereo,
                                   device=device, progress=progress, max_stretch=cfg.max_stretch)
    stats["box"] = box.tolist()
    z0 = ground_height(cloud, below=street_ceiling([f.c2w[2, 3] for f in scene.ground]))
    stats["street_height_m"] = z0
    if z0 is None and len(cloud):
        log.warning("%s: no street in the fused cloud under the ground cameras: the street prior is off", scene.name)
    if z0 is not None and cfg.ground_snap_m > 0:
        cloud = snap_to_plane(cloud, (np.array([0.0, 0.0, 1.0]), z0), cfg.ground_snap_m)
    stats["points"] = len(cloud)
    return cloud, stats


def geometry_render(params: dict, cam, background: np.ndarray, *, opacity: float, near: float,
                    device="cpu", colour_map=None) -> np.ndarray:
    """The fused cloud's surfels (`splat.surfels`) seen from `cam`: float32 [H, W, 5] = colour
    over `background` [H, W, 3] (after `colour_map`, if given), planar depth (m; 0 where nothing
    projects) and coverage alpha in [0, 1]."""
    out = splat.render_surfels(params, cam, opacity=opacity, near=near, device=device)
    colour = out["colour"] if colour_map is None else colour_map(out["colour"])
    rgb = splat.over(colour, out["alpha"], background)
    return np.concatenate([rgb, out["depth"][..., None], out["alpha"][..., None]], -1).astype(np.float32)


class MVS(Method):
    """The fused cloud's discs in the ground cameras. With `geometry=True` (gvg's prior) each
    frame is `geometry_render`'s [H, W, 5], the colour with the discs' depth and coverage, and
    the method is named "mvs-geometry" (its renders are cached under that name)."""

    name = "mvs"
    version = "0.1"
    presets = PRESETS
    scene_checkpoint = "cloud.npz"

    def __init__(self, config, workdir, *, geometry: bool = False, **kw):
        super().__init__(config, workdir, **kw)
        self.geometry = geometry
        if geometry:
            self.name = "mvs-geometry"
        self._splats: dict[str, tuple[dict, np.ndarray | None]] = {}  # scene -> (surfels, ground colour)
        self.colour_map = ColourMap()
        self.backgrounds: Backgrounds | None = None

    # ---------------------------------------------------------------- train split
    def fit_train(self, dataset: Dataset) -> None:
        cfg = self.config
        lanes = dataset.split("train")[: max(cfg.train_lanes, 0)]
        if not lanes:
            log.info("appearance: no train lanes used (train_lanes=%d): identity colour map", cfg.train_lanes)
            return
        self.use_threads()

        def save(fit, path):
            path.write_text(json.dumps({"colour_map": fit[0].to_dict(), "backgrounds": fit[1].to_dict()}, indent=2))

        def load(path):
            d = fileio.read_json(path, allow_nan=True)
            return ColourMap.from_dict(d["colour_map"]), Backgrounds.from_dict(d["backgrounds"])

        (self.colour_map, self.backgrounds), info = self.checkpointed(
            self.train_dir / "appearance.json", lambda: self._learn_appearance(lanes), save=save, load=load,
            stats=self.train_dir / "fit.json")
        log.info("appearance: fitted on %d train lanes in %.0f s (sky %s, ground %s)",
                 len(info.get("train_lanes", [])), info.get("seconds", 0.0),
                 np.round(self.backgrounds.sky, 3).tolist(), np.round(self.backgrounds.ground, 3).tolist())

    def _learn_appearance(self, lanes: list[Scene]) -> tuple[tuple[ColourMap, Backgrounds], dict]:
        """The colour map and backgrounds from each lane's reconstruction rendered into its ground cameras."""
        cfg = self.config
        acc = AppearanceFit(seed=self.seed)
        grey = np.full(3, 0.5, np.float32)
        # Each lane's cloud is a scene fit (checkpointed like a test lane's), `jobs` lanes at once.
        self.fit_scenes(lanes)
        for lane in lanes:
            params = self._surfel_params(self.scene_model(lane))
            for seq in lane.sequences.values():
                for f in seq:
                    cam = f.camera()
                    rgb, alpha = splat.render_cloud(params, cam, opacity=cfg.opacity, near=cfg.render_near_m,
                                                    device=self.device)
                    acc.add(rgb, alpha, f.image(), cam)
        return acc.result(grey, grey), {"train_lanes": [lane.name for lane in lanes]}

    # ---------------------------------------------------------------- test scenes
    def _surfel_params(self, cloud: PointCloud) -> dict:
        cfg = self.config
        params = splat.surfels(splat.voxel_downsample(cloud, cfg.voxel_m), size=cfg.disc_size)
        return {k: v.to(self.device) for k, v in params.items()}

    def fit_scene_model(self, scene: Scene, *, progress: bool) -> tuple[PointCloud, dict]:
        cloud, stats = reconstruct(scene, self.config, device=self.device, progress=progress)
        if len(cloud) == 0:
            log.warning("%s: MVS fused no point (%s): every ground frame will be the background", scene.name, stats)
        log.info("%s: %d fused points (coverage %.2f raw, %.2f consistent)", scene.name, len(cloud),
                 stats["raw_coverage"], stats["filtered_coverage"])
        return cloud, stats

    def save_scene_model(self, cloud: PointCloud, path: Path) -> None:
        with open(path, "wb") as fh:
            np.savez(fh, **dataclasses.asdict(cloud))

    def load_scene_model(self, path: Path) -> PointCloud:
        with np.load(path) as z:
            return PointCloud(**{k: z[k] for k in ("xyz", "rgb", "normals", "footprint")})

    def _splat(self, scene: Scene) -> tuple[dict, np.ndarray | None]:
        """The scene's cloud as surfels on the device, and its ground colour."""
        if scene.name not in self._splats:
            cloud = self.scene_model(scene)
            self._splats[scene.name] = (self._surfel_params(cloud), splat.ground_colour(cloud))
        return self._splats[scene.name]

    def _backgrounds(self, scene: Scene, ground: np.ndarray | None) -> Backgrounds:
        if self.backgrounds is not None:
            return self.backgrounds
        sky = sky_colour(list(scene.aerial))
        return Backgrounds(sky, ground if ground is not None else sky)

    @torch.no_grad()
    def render_sequence(self, scene: Scene, sequence: Sequence) -> Iterator[np.ndarray]:
        cfg = self.config
        self.use_threads()
        params, ground = self._splat(scene)
        bgs = self._backgrounds(scene, ground)
        for frame in sequence:
            cam = frame.camera()
            # The colour map corrects what the aerial views saw; the background is already a
            # ground-view colour.
            out = geometry_render(params, cam, bgs.image(cam), opacity=cfg.opacity, near=cfg.render_near_m,
                                  device=self.device, colour_map=self.colour_map)
            yield out if self.geometry else np.ascontiguousarray(out[..., :3])
