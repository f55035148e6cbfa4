"""`mean-frame`: the floor. Every test frame is the per-pixel mean of the train split's ground
frames: no scene, no geometry, no diversity. A method that does not beat it on a per-frame
metric has learned nothing a constant image does not already carry; every leaderboard shows it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from reference.method import Method
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
    kind = "floor"

    def components(self) -> list[str]:
        return ["every frame the per-pixel mean of the train split's ground frames"]
    version = "0.1"
    presets = PRESETS

    def __init__(self, config, workdir, **kw):
        super().__init__(config, workdir, **kw)
        self.mean: np.ndarray | None = None

    def fit_train(self, dataset: Dataset) -> None:
        def save(mean, path):
            with open(path, "wb") as fh:
                np.save(fh, mean)

        self.mean, info = self.checkpointed(self.train_dir / "mean.npy", lambda: self._mean(dataset), save=save,
                                            load=np.load, stats=self.train_dir / "fit.json")
        log.info("mean-frame: mean of %s train ground frames (%.1f s)", info.get("frames"), info.get("seconds", 0.0))

    def _mean(self, dataset: Dataset) -> tuple[np.ndarray, dict]:
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
        return (acc / len(frames)).astype(np.float32), {"frames": len(frames)}

    def fit_scene_model(self, scene: Scene, *, progress: bool) -> tuple[None, dict]:
        """Nothing per scene: every frame is the train mean."""
        return None, {}

    def render_sequence(self, scene: Scene, sequence: Sequence) -> Iterator[np.ndarray]:
        if self.mean is None:
            raise RuntimeError("mean-frame: render before fit_train")
        for f in sequence:
            if (f.height, f.width) != self.mean.shape[:2]:
                raise UserError(f"{f.file}: test frame is {f.width}x{f.height}, the train mean is "
                                f"{self.mean.shape[1]}x{self.mean.shape[0]} (mean-frame needs one frame size)")
            yield self.mean.copy()
