"""The interface every reference method implements, so `reproduce` can drive any of them.

Life cycle (driven by `reference.reproduce`):

1. `fit_train(dataset)`: learn what carries across scenes from the *train* split (a diffusion
   model, say). Optional; methods that only reconstruct a scene leave it empty.
2. `fit_scene(scene)`: per test scene (a lane). Only the scene's aerial images and poses may be
   used, plus the *poses and intrinsics* of its ground cameras (never their pixels).
3. `render_sequence(scene, sequence)`: yield one float32 [H, W, 3] image in [0, 1] per ground
   frame of the sequence, in order.

Configs are dataclasses; presets are named configs (`smoke`, `small`, `paper`) saved with
every run so a run can be repeated from its own output folder.
"""

from __future__ import annotations

import abc
import dataclasses
import logging
from pathlib import Path
from typing import Any, ClassVar, Iterator

import numpy as np

from skyeyes_bench.data.layout import Dataset, Scene, Sequence


class Method(abc.ABC):
    name: ClassVar[str]
    version: ClassVar[str] = "0.1"
    #: preset name -> config dataclass instance
    presets: ClassVar[dict[str, Any]]

    def __init__(self, config: Any, workdir: Path, *, seed: int = 0):
        self.config = config
        self.workdir = Path(workdir)
        self.seed = seed
        self.workdir.mkdir(parents=True, exist_ok=True)

    @classmethod
    def from_preset(cls, preset: str, workdir: Path, *, seed: int = 0, **overrides) -> "Method":
        from skyeyes_bench.registry import lookup

        config = dataclasses.replace(lookup(cls.presets, preset, f"preset of method {cls.name!r}"), **overrides)
        return cls(config, workdir, seed=seed)

    def scene_dir(self, scene: Scene) -> Path:
        """Where a method keeps what it fitted on `scene` (checkpoints, fit.json)."""
        return self.workdir / "scenes" / scene.name

    def cached_seconds(self) -> float:
        """Original seconds of the work this instance took from caches instead of doing (stages,
        priors), so a run's reported time is what producing its result cost. Default: none."""
        return 0.0

    def scene_fit_seconds(self, scene: Scene, took: float) -> float:
        """What fitting `scene` cost: the seconds its fit recorded (`scene_stats[...]["fit_seconds"]`;
        a fit resumed from its checkpoint records its first run's), else `took`, the wall time
        of the call."""
        return float(getattr(self, "scene_stats", {}).get(scene.name, {}).get("fit_seconds", took))

    def resume_scene(self, scene: Scene, file: str, load) -> bool:
        """Resume: if `scene_dir(scene)/file` (a fit's last, atomically written output) exists,
        call `load(scene)` and return True; else False (fit it)."""
        ckpt = self.scene_dir(scene) / file
        if not ckpt.is_file():
            return False
        load(scene)
        logging.getLogger(type(self).__module__).info("%s: reusing %s", scene.name, ckpt)
        return True

    def config_dict(self) -> dict:
        return dataclasses.asdict(self.config)

    def fit_train(self, dataset: Dataset) -> None:  # noqa: B027  (optional hook)
        """Learn from the train split. Default: nothing to learn across scenes."""

    @abc.abstractmethod
    def fit_scene(self, scene: Scene) -> None:
        """Fit on one test scene's aerial views (and its ground camera poses, not pixels)."""

    @abc.abstractmethod
    def render_sequence(self, scene: Scene, sequence: Sequence) -> Iterator[np.ndarray]:
        """Yield float32 [H, W, 3] images in [0, 1], one per frame of `sequence`, in order."""
