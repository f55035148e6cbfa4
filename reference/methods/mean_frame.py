"""`mean-frame`: the floor. Every test frame is the per-pixel mean of the train split's ground
frames: no scene, no geometry, no diversity. A method that does not beat it on a per-frame
metric has learned nothing a constant image does not already carry; every leaderboard shows it.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from reference.method import Method
from skyeyes_bench import fileio
from skyeyes_bench.data.layout import Dataset, Scene, Sequence
from skyeyes_bench.errors import UserError

log = logging.getLogger(__name__)


@dataclass
class MeanFrameConfig:
    """Attributes:
        max_frames: at most this many train ground frames enter the mean (evenly spaced; 0: all).
    """

    max_frames: int = 0


PRESETS = {"smoke": MeanFrameConfig(), "small": MeanFrameConfig(), "paper": MeanFrameConfig()}


class MeanFrame(Method):
    name = "mean-frame"
    version = "0.1"
    presets = PRESETS

    def __init__(self, config, workdir, *, seed: int = 0):
        super().__init__(config, workdir, seed=seed)
        self.mean: np.ndarray | None = None
        self.scene_stats: dict[str, dict] = {}

    def fit_train(self, dataset: Dataset) -> None:
        path = self.workdir / "mean.npy"
        if path.is_file():
            self.mean = np.load(path)
            return
        t0 = time.perf_counter()
        frames = [f for seq in dataset.sequences("train") for f in seq]
        if not frames:
            raise UserError(f"{dataset.root}: mean-frame needs ground frames in the train split; it has none")
        if self.config.max_frames and len(frames) > self.config.max_frames:
            frames = [frames[i] for i in np.linspace(0, len(frames) - 1, self.config.max_frames).round().astype(int)]
        size = (frames[0].height, frames[0].width)
        acc = np.zeros(size + (3,), np.float64)
        for f in frames:
            if (f.height, f.width) != size:
                raise UserError(f"{f.path}: train ground frame is {f.width}x{f.height}, expected {size[1]}x{size[0]} "
                                "like the first one (mean-frame needs one frame size)")
            acc += f.image()
        self.mean = (acc / len(frames)).astype(np.float32)
        with fileio.atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.save(fh, self.mean)
        log.info("mean-frame: mean of %d train ground frames (%.1f s)", len(frames), time.perf_counter() - t0)

    def fit_scene(self, scene: Scene) -> None:
        self.scene_stats[scene.name] = {"fit_seconds": 0.0}

    def render_sequence(self, scene: Scene, sequence: Sequence) -> Iterator[np.ndarray]:
        if self.mean is None:
            raise RuntimeError("mean-frame: render before fit_train")
        for f in sequence:
            if (f.height, f.width) != self.mean.shape[:2]:
                raise UserError(f"{f.file}: test frame is {f.width}x{f.height}, the train mean is "
                                f"{self.mean.shape[1]}x{self.mean.shape[0]} (mean-frame needs one frame size)")
            yield self.mean.copy()
