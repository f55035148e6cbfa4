"""The fused MVS cloud of a lane as a part any method may use (Schoenberger et al. 2016): the
`mvs` row, gvg's geometry, and what the learned appearance of the reconstruction methods is fitted
on (`learn_appearance`). Dense depth for every aerial view from its neighbours, kept where other
views agree, fused into one coloured cloud of the region the ground cameras see
(`reference.common.mvs_start`, `reference.common.geometry`), drawn into each ground camera as
surface discs sized by each point's footprint. Pixels no disc covers show the background.

What it learns on the train split (`fit_train`, `train_lanes` of them): the same reconstruction of
each train lane rendered into its ground cameras gives (render, truth) pairs, from which it fits a
global colour map (aerial haze -> ground colours) and the two background colours
(`reference.common.appearance`). `train_lanes=0` turns that off: backgrounds then come from the
test lane alone (sky: aerial pixels above the horizon; ground: the cloud's lowest layer).

Checkpoints (`Method.checkpointed`): the appearance in `<workdir>/train/appearance.json`, each
scene's fused cloud in `<workdir>/scenes/<scene>/cloud.npz`, each with its `fit.json`; a later run
on the same workdir reuses them.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import Iterator

import numpy as np
import torch

from reference.common.appearance import Appearance, AppearanceFit, Backgrounds, ColourMap
from reference.common.geometry import splat
from reference.common.geometry.cloud import PointCloud
from reference.common.mvs_start import PRESETS, MVSMethodConfig, reconstruct
from reference.method import Method
from skyeyes_bench import inputfiles
from skyeyes_bench.data.layout import Dataset, Scene, Sequence

log = logging.getLogger(__name__)


def geometry_render(params: dict, cam, background: np.ndarray, *, opacity: float, near: float,
                    device="cpu", colour_map=None) -> np.ndarray:
    """The fused cloud's surfels (`splat.surfels`) seen from `cam`: float32 [H, W, 5] = colour
    over `background` [H, W, 3] (after `colour_map`, if given), planar depth (m; 0 where nothing
    projects) and coverage alpha in [0, 1]."""
    out = splat.render_surfels(params, cam, opacity=opacity, near=near, device=device)
    colour = out["colour"] if colour_map is None else colour_map(out["colour"])
    rgb = splat.over(colour, out["alpha"], background)
    return np.concatenate([rgb, out["depth"][..., None], out["alpha"][..., None]], -1).astype(np.float32)


class MVSCloud(Method):
    """The fused cloud's discs in the ground cameras. With `geometry=True` (gvg's prior) each
    frame is `geometry_render`'s [H, W, 5], the colour with the discs' depth and coverage, and
    the part is named "mvs-geometry" (its renders are cached under that name)."""

    name = "mvs"
    version = "0.1"
    presets = PRESETS
    scene_checkpoint = "cloud.npz"

    def __init__(self, config: MVSMethodConfig, workdir, *, geometry: bool = False, **kw):
        super().__init__(config, workdir, **kw)
        self.geometry = geometry
        if geometry:
            self.name = "mvs-geometry"
        self._splats: dict[str, tuple[dict, np.ndarray | None]] = {}  # scene -> (surfels, ground colour)
        self.appearance = Appearance()

    # ---------------------------------------------------------------- train split
    def fit_train(self, dataset: Dataset) -> None:
        cfg = self.config
        lanes = dataset.split("train")[: max(cfg.train_lanes, 0)]
        if not lanes:
            log.info("appearance: no train lanes used (train_lanes=%d): identity colour map", cfg.train_lanes)
            return
        self.use_threads()

        def save(fit, path):
            path.write_text(json.dumps({"colour_map": fit.colour_map.to_dict(),
                                        "backgrounds": fit.backgrounds.to_dict()}, indent=2))

        def load(path):
            d = inputfiles.read_json(path, allow_nan=True)
            return Appearance(ColourMap.from_dict(d["colour_map"]), Backgrounds.from_dict(d["backgrounds"]))

        self.appearance, info = self.checkpointed(
            self.train_dir / "appearance.json", lambda: self._learn_appearance(lanes), save=save, load=load,
            stats=self.train_dir / "fit.json")
        bgs = self.appearance.backgrounds
        log.info("appearance: fitted on %d train lanes in %.0f s (sky %s, ground %s)",
                 len(info.get("train_lanes", [])), info.get("seconds", 0.0),
                 np.round(bgs.sky, 3).tolist(), np.round(bgs.ground, 3).tolist())

    def _learn_appearance(self, lanes: list[Scene]) -> tuple[Appearance, dict]:
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
        return Appearance(*acc.result(grey, grey)), {"train_lanes": [lane.name for lane in lanes]}

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

    @torch.no_grad()
    def render_sequence(self, scene: Scene, sequence: Sequence) -> Iterator[np.ndarray]:
        cfg = self.config
        self.use_threads()
        params, ground = self._splat(scene)
        bgs = self.appearance.background(scene, ground)
        for frame in sequence:
            cam = frame.camera()
            # The colour map corrects what the aerial views saw; the background is already a
            # ground-view colour.
            out = geometry_render(params, cam, bgs.image(cam), opacity=cfg.opacity, near=cfg.render_near_m,
                                  device=self.device, colour_map=self.appearance.colour_map)
            yield out if self.geometry else np.ascontiguousarray(out[..., :3])


def learn_appearance(owner, dataset) -> Appearance:
    """The appearance `owner` (a `Method` whose config is a `SceneConfig` with an `mvs_preset`)
    learns on the train split: the fused clouds (`MVSCloud`) of its `train_lanes` train lanes at
    that stereo preset in owner's region, fitted in `<workdir>/appearance`, its fits there reused.
    The seconds it took from caches count in `owner.cached_s`."""
    cfg = owner.config
    if cfg.train_lanes <= 0:
        return Appearance()
    clouds = MVSCloud.from_preset(cfg.mvs_preset, owner.workdir / "appearance", seed=owner.seed,
                                  progress=owner.progress, train_lanes=cfg.train_lanes, device=owner.device,
                                  margin_m=cfg.margin_m, z_min=cfg.z_min, z_max=cfg.z_max)
    clouds.jobs = owner.jobs
    clouds.fit_train(dataset)
    owner.took_from_cache(clouds.cached_s)
    return clouds.appearance
