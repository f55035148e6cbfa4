"""Write the canonical dataset layout (see `skyeyes_bench.data.layout`) all at once.

`DatasetWriter` fills a temporary folder and moves it into place only when complete (and, with
`validate=True`, only when `validate_dataset` finds no problem in it).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .. import imagefiles, outputfiles
from ..errors import ValidationError
from .layout import DATASET_FILE, KINDS, SCENE_FILE, layer_file, validate_dataset


def _c2w_list(c2w: np.ndarray) -> list[list[float]]:
    m = np.asarray(c2w, dtype=np.float64)
    assert m.shape == (4, 4), m.shape
    return [[float(v) for v in row] for row in m]


class SceneWriter:
    """Adds frames to one scene folder; `DatasetWriter.scene()` makes it."""

    def __init__(self, root: Path, name: str, intrinsics: dict[str, dict], meta: dict | None):
        self.root = root / name
        self.name = name
        self.intrinsics = {k: dict(v) for k, v in intrinsics.items()}
        self.meta = dict(meta or {})
        self.entries: dict[str, list[dict]] = {k: [] for k in KINDS}
        self.closed = False
        self.root.mkdir(parents=True, exist_ok=False)

    def _add(self, kind: str, image, c2w, depth, semantics, extra: dict, file: str | None) -> str:
        file = file or f"{kind}/{len(self.entries[kind]):06d}.png"
        (self.root / kind).mkdir(exist_ok=True)
        if isinstance(image, (str, os.PathLike)):
            _copy(Path(image), self.root / file)
        else:
            imagefiles.write_image(self.root / file, image)
        if depth is not None:
            imagefiles.write_depth(self.root / layer_file(file, "depth"), depth)
        if semantics is not None:
            imagefiles.write_labels(self.root / layer_file(file, "semantics"), semantics)
        self.entries[kind].append({"file": file, "c2w": _c2w_list(c2w), **extra})
        return file

    def add_aerial(self, image, c2w, *, depth=None, semantics=None, file: str | None = None, **extra) -> str:
        """image: float [H, W, 3] in [0,1], uint8, or a path to an 8-bit PNG to copy."""
        return self._add("aerial", image, c2w, depth, semantics, extra, file)

    def add_ground(self, image, c2w, *, sequence: str, index: int, depth=None, semantics=None,
                   file: str | None = None, **extra) -> str:
        return self._add("ground", image, c2w, depth, semantics, {"sequence": sequence, "index": int(index), **extra}, file)

    def close(self) -> None:
        """Write scene.json (`DatasetWriter.finish` does it for scenes not closed yet)."""
        outputfiles.write_json(self.root / SCENE_FILE, {"intrinsics": self.intrinsics, **self.entries, "meta": self.meta})
        self.closed = True


def _copy(src: Path, dst: Path) -> None:
    import shutil

    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dst)


class DatasetWriter(outputfiles.AtomicFolderWriter):
    """Writes a dataset into a temporary folder and moves it into place only when complete.

    ```
    with DatasetWriter(out, name="synthtown-small", protocol="synthtown@1") as w:
        s = w.scene("train-0-lane00", {"ground": {...}, "aerial": {...}}, meta={...})
        s.add_ground(img, c2w, sequence="yaw000", index=0, depth=d)
        s.close()
        w.finish(splits={"train": [...], "test": [...]}, meta={...})
    ```
    """

    def __init__(self, root: str | os.PathLike, *, name: str, protocol: str, overwrite: bool = False,
                 validate: bool = False):
        """validate: run `validate_dataset` on the finished folder before moving it into place;
        any problem raises ValidationError and nothing is written."""
        super().__init__(root, overwrite=overwrite)
        self.name, self.protocol, self.validate = name, protocol, validate
        self.scenes: list[str] = []
        self._writers: list[SceneWriter] = []

    def scene(self, name: str, intrinsics: dict[str, dict], meta: dict | None = None) -> SceneWriter:
        if name in self.scenes:
            raise ValueError(f"scene {name!r} written twice")
        self.scenes.append(name)
        writer = SceneWriter(self.root, name, intrinsics, meta)
        self._writers.append(writer)
        return writer

    def finish(self, splits: dict[str, list[str]], meta: dict | None = None) -> None:
        for writer in self._writers:
            if not writer.closed:
                writer.close()
        outputfiles.write_json(self.root / DATASET_FILE, {
            "name": self.name, "protocol": self.protocol, "splits": splits,
            "scenes": self.scenes, "meta": dict(meta or {}),
        })
        self._finished = True

    def _before_commit(self) -> None:
        if self.validate:
            _, problems = validate_dataset(self.root, check_pixels=False)
            if problems:
                raise ValidationError(f"dataset {self.final} (not written)", problems)
