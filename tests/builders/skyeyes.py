"""A tiny hand-made dataset and a TEST-ONLY stand-in prior for the Skyeyes method tests (no tests here).

The stand-in is the ground-truth frame blurred and noised; the real method uses the SuGaR prior,
fitted on aerial views only."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reference.common.gaussians.scene_geometry import GaussianGeometry
from reference.method import Method
from skyeyes_bench.cameras import Camera
from skyeyes_bench.data.writer import DatasetWriter

SIZE = 16


def make_tiny_dataset(root: Path, frames: int = 6, seqs: int = 2) -> Path:
    """Two lanes (train, test), smooth images that drift along each sequence."""
    rng = np.random.default_rng(0)
    intr = {"width": SIZE, "height": SIZE, "fx": SIZE / 2, "fy": SIZE / 2, "cx": SIZE / 2, "cy": SIZE / 2}
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] / SIZE
    with DatasetWriter(root, name="tiny", protocol="synthtown@1") as w:
        for sname in ["train-0-lane00", "test-0-lane00"]:
            s = w.scene(sname, {"ground": intr, "aerial": intr})
            for a in range(3):
                cam = Camera.from_ypr([a * 4.0, 0, 52], 0, -45, fov_deg=90, width=SIZE, height=SIZE)
                s.add_aerial(rng.random((SIZE, SIZE, 3)).astype(np.float32), cam.c2w)
            for k in range(seqs):
                for i in range(frames):
                    cam = Camera.from_ypr([i * 2.0, 0, 2], 45 * k, 0, fov_deg=90, width=SIZE, height=SIZE)
                    img = np.stack([(xx + 0.1 * i) % 1, yy, np.full_like(xx, 0.3 * k + 0.1)], -1)
                    s.add_ground(img.astype(np.float32), cam.c2w, sequence=f"yaw{45 * k:03d}", index=i)
            s.close()
        w.finish(splits={"train": ["train-0-lane00"], "test": ["test-0-lane00"]})
    return root


def render_all(method, dataset) -> dict:
    """{sequence id: frames [N, H, W, 3]} of every test sequence: each test scene fitted, then
    its sequences rendered in order (the method's fit_train done already)."""
    out = {}
    for scene in dataset.split("test"):
        method.fit_scene(scene)
        for seq in scene.sequences.values():
            out[seq.id] = np.stack(list(method.render_sequence(scene, seq)))
    return out


class StandInPrior(GaussianGeometry, Method):
    """TEST-ONLY stand-in for SuGaR: ground truth, box-blurred and noised, and as its fitted
    scene a Gaussian prior's model (its depth and points, `GaussianGeometry`, read by the additions): a grid of
    grey Gaussians on the street 1.6 m under the ground cameras, nothing above it (the sky).
    Counts its calls."""

    name = "stand-in-prior"
    presets = {"default": {}}
    #: the street's height under the ground cameras (m)
    CAMERA_HEIGHT_M = 1.6

    def __init__(self, workdir: Path, seed: int = 0):
        import types

        # what a Gaussian prior's config gives `GaussianGeometry.depth`
        super().__init__(types.SimpleNamespace(sh_degree=0, render_near_m=0.05), workdir, seed=seed)
        self.fitted: list[str] = []

    def config_dict(self) -> dict:
        return {"blur": 3, "noise": 0.1}

    def fit_scene_model(self, scene, *, progress):
        from reference.common.gaussians.model import GaussianModel

        self.fitted.append(scene.name)
        pos = np.array([f.camera().c2w[:3, 3] for f in scene.ground])
        gx, gy = np.meshgrid(np.arange(pos[:, 0].min() - 20, pos[:, 0].max() + 20, 0.5),
                             np.arange(pos[:, 1].min() - 20, pos[:, 1].max() + 20, 0.5))
        xyz = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, pos[:, 2].min() - self.CAMERA_HEIGHT_M)], 1)
        return (GaussianModel.from_points(xyz, np.full_like(xyz, 0.5), 0, opacity=0.9, max_scale=0.5),), {}

    def render_sequence(self, scene, sequence):
        from scipy.ndimage import uniform_filter

        rng = np.random.default_rng(len(sequence.name))
        for f in sequence.frames:
            img = uniform_filter(f.image(), size=(3, 3, 1))
            yield np.clip(img + rng.normal(0, 0.1, img.shape), 0, 1).astype(np.float32)


class StandInGeometryPrior(StandInPrior):
    """TEST-ONLY stand-in for gvg's `mvs` geometry: per frame [H, W, 5] = the stand-in colour, a
    depth of 4 m and coverage 1 below the image's top quarter, depth 0 and coverage 0 above it
    (the colour is then the sky's grey)."""

    name = "stand-in-geometry"

    def render_sequence(self, scene, sequence):
        for img in super().render_sequence(scene, sequence):
            h = img.shape[0]
            alpha = np.ones(img.shape[:2], np.float32)
            alpha[: h // 4] = 0.0
            img = np.where(alpha[..., None] > 0, img, 0.5).astype(np.float32)
            yield np.concatenate([img, (4.0 * alpha)[..., None], alpha[..., None]], -1)
