"""The fused MVS cloud of a lane: the `mvs` method's reconstruction, the start of `gaussians3d`,
`sugar` and `nerf` (their `mvs_preset` names one of the stereo `PRESETS` here), and what the
learned appearance is fitted on (`reference.common.appearance`).

Dense depth for every aerial view from its neighbours, kept where other views agree, fused into
one coloured cloud of the region the ground cameras see (`reference.common.geometry.mvs`), its
street snapped to its height (`ground_snap_m`).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from reference.common.geometry import mvs as gmvs
from reference.common.geometry.cloud import PointCloud, ground_height, snap_to_plane, street_ceiling
from reference.common.scene import SceneConfig, region_box
from skyeyes_bench.data.layout import Scene

log = logging.getLogger(__name__)


@dataclass
class MVSMethodConfig(SceneConfig, gmvs.MVSConfig):
    """Stereo settings (`MVSConfig`) plus the scene's (`SceneConfig`: region, train lanes, device,
    threads; `render_near_m`: discs nearer a ground camera than this are not drawn) and how the
    fused cloud is kept and drawn.

    Attributes:
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
    """

    voxel_m: float = 0.25
    max_stretch: float = 1.0
    disc_size: float = 1.0
    opacity: float = 0.98
    ground_snap_m: float = 2.0


PRESETS: dict[str, MVSMethodConfig] = {
    # Seconds at 48x48 (tests, CI).
    "smoke": MVSMethodConfig(planes=32, num_sources=4, train_lanes=1, min_consistent=1),
    # The CPU default at 128x128 (about 2.5 CPU-minutes per lane of 64 aerial views; docs/log/runs-2026.md).
    "small": MVSMethodConfig(),
    # The start of the splatting methods and their appearance at `small`: half the cost for the same depth
    # accuracy, fewer points; chosen on a synthtown@2 test lane before a validation split existed; see
    # docs/log/runs-2026.md.
    "fast": MVSMethodConfig(planes=64, num_sources=4),
    # GPU users at 512x512: more planes and sources, every train lane.
    "paper": MVSMethodConfig(planes=256, num_sources=8, window=7, train_lanes=1000, voxel_m=0.1),
}


def reconstruct(scene: Scene, cfg: MVSMethodConfig, *, device: str, aerial: list | None = None,
                progress: bool = False) -> tuple[PointCloud, dict]:
    """Fused cloud of one lane (cropped to its region box) on `device`, and the stereo stats;
    `aerial`: the views to use (default all of the scene's)."""
    aerial = list(scene.aerial) if aerial is None else aerial
    box = region_box(scene, cfg)
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


def start_cloud(scene: Scene, cfg: SceneConfig, *, device: str, aerial: list) -> PointCloud:
    """The fused cloud a fit starts from: the stereo preset `cfg.mvs_preset` in `cfg`'s region, of
    the `aerial` views."""
    mcfg = dataclasses.replace(PRESETS[cfg.mvs_preset], margin_m=cfg.margin_m, z_min=cfg.z_min, z_max=cfg.z_max)
    cloud, _ = reconstruct(scene, mcfg, device=device, aerial=aerial)
    return cloud
