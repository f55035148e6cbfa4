"""What every geometry method (`mvs`, `gaussians3d`, `sugar`, `nerf`) shares about a scene: the
config fields of its region and of its run (`SceneConfig`, which their configs inherit), the
region box those fields make, and the aerial views a fit trains on."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reference.common.geometry import region


@dataclass
class SceneConfig:
    """The region the ground cameras see, what is learned on the train split, the ground renders'
    near plane, and where and on how many threads the method runs.

    Attributes:
        margin_m: horizontal margin around the ground cameras of the kept region (m).
        z_min, z_max: vertical extent of the kept region (world z, m).
        train_lanes: train lanes reconstructed to learn the colour map and backgrounds
            (`reference.common.appearance`; 0: none, backgrounds from the test lane alone and
            no colour map).
        render_near_m: near plane of the ground renders (m): what lies nearer a ground camera is
            not drawn (a method sets its own default and says why).
        device: torch device of the fit and the renders ("cpu", "cuda", ...).
        threads: torch intra-op threads on the CPU. 1 by default: on a shared 2-core machine a
            second OpenMP thread made the rasterizer up to 7x slower (spin-waiting under
            contention), and an `mvs` smoke run 95 s instead of 14 s.
    """

    margin_m: float = 30.0
    z_min: float = -1.0
    z_max: float = 40.0
    train_lanes: int = 2
    render_near_m: float = 0.5
    device: str = "cpu"
    threads: int = 1


def region_box(scene, cfg: SceneConfig) -> np.ndarray:
    """The scene's region box [2, 3] (`region.region_box` of its ground cameras, `cfg`'s margin
    and heights)."""
    return region.region_box(list(scene.ground), cfg.margin_m, (cfg.z_min, cfg.z_max))


def held_out(aerial: list, every: int) -> list:
    """Every `every`-th of the `aerial` views (0: none), held out of a fit for its curves."""
    return [f for i, f in enumerate(aerial) if every and i % every == every - 1]


@dataclass
class FitConfig(SceneConfig):
    """`SceneConfig` of a method that fits a model on a lane's aerial views (`gaussians3d`,
    `sugar`, `nerf`).

    Attributes:
        mvs_preset: the stereo preset (`reference.common.mvs_start.PRESETS`) of the MVS start and
            of the appearance learned on the train split (`reference.common.appearance`).
        holdout_every: hold out every k-th aerial view from training (0: none), for curves
            (`held_out`).
    """

    mvs_preset: str = "small"
    holdout_every: int = 0
