"""What carries from aerial colours to ground colours, learned on the train split.

SynthTown's aerial views look through 50-80 m of haze, its ground views through a few metres,
so a street lifted from the aerial views is paler and bluer than the ground truth (docs/reproduce.md,
"Method `mvs`": a colour map fitted on the train lanes adds ~2 dB PSNR to a true-depth reconstruction). A
reconstruction method may learn that map on the train split (`Method.fit_train`) and apply it to
every render; it changes colours only, never where things are.

- `ColourMap`: a global quadratic map of RGB, least squares with a small ridge, fitted on
  (render, ground truth) pixel pairs where the render covers the pixel.
- `Backgrounds`: the colour of uncovered pixels above and below the horizon, the mean ground
  truth colour there on the train lanes (`sky_colour`: from a lane's aerial views, without them).
- `Appearance`: both, as a reconstruction method holds them (`reference.common.mvs_cloud.learn_appearance`:
  learned from the fused MVS clouds of train lanes, as `gaussians3d`, `sugar` and `nerf` do).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def quadratic_features(rgb: np.ndarray) -> np.ndarray:
    """[..., 3] -> [..., 10]: 1, r, g, b, r^2, g^2, b^2, rg, rb, gb."""
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return np.stack([np.ones_like(r), r, g, b, r * r, g * g, b * b, r * g, r * b, g * b], -1)


@dataclass
class ColourMap:
    """out = features(rgb) @ coef, clipped to [0, 1]; the identity when fitted on nothing."""

    coef: np.ndarray = field(default_factory=lambda: np.vstack([np.zeros((1, 3)), np.eye(3), np.zeros((6, 3))]))

    @classmethod
    def fit(cls, pred: np.ndarray, target: np.ndarray, *, ridge: float = 1e-3) -> "ColourMap":
        """Least squares of target [N, 3] on quadratic_features(pred [N, 3]); the ridge pulls
        towards the identity map (so too few pixels give the identity, never a wild map)."""
        pred = np.asarray(pred, np.float64).reshape(-1, 3)
        target = np.asarray(target, np.float64).reshape(-1, 3)
        ident = cls().coef
        if len(pred) < 10:
            return cls()
        x = quadratic_features(pred)
        lam = ridge * len(pred)
        a = x.T @ x + lam * np.eye(10)
        b = x.T @ target + lam * ident
        return cls(np.linalg.solve(a, b))

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        out = quadratic_features(np.asarray(rgb, np.float64)) @ self.coef
        return np.clip(out, 0.0, 1.0).astype(np.float32)

    def to_dict(self) -> dict:
        return {"coef": self.coef.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "ColourMap":
        coef = np.asarray(d["coef"], np.float64)
        if coef.shape != (10, 3):
            raise ValueError(f"colour map coef: expected shape (10, 3), got {coef.shape}")
        return cls(coef)


def above_horizon(cam) -> np.ndarray:
    """[H, W] bool: the pixel's ray points up (world z > 0)."""
    _, d = cam.rays(normalize=False)
    return (d[:, 2] > 0).reshape(cam.height, cam.width)


@dataclass
class Backgrounds:
    """Colours [3] of pixels no surface covers: `sky` above the horizon, `ground` below."""

    sky: np.ndarray
    ground: np.ndarray

    def image(self, cam) -> np.ndarray:
        """float32 [H, W, 3] for `cam`."""
        up = above_horizon(cam)
        return np.where(up[..., None], self.sky, self.ground).astype(np.float32)

    def to_dict(self) -> dict:
        return {"sky": np.asarray(self.sky).tolist(), "ground": np.asarray(self.ground).tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "Backgrounds":
        return cls(np.asarray(d["sky"], np.float32), np.asarray(d["ground"], np.float32))


def sky_colour(frames: list) -> np.ndarray:
    """Mean colour [3] of the aerial image rows (of `frames`, dataset frames) that look above the
    horizon: the ray through the row at the principal point's column climbs (world dz > 0.05 at
    camera z = 1). Grey if no row does; the background of a method that learned none."""
    acc, n = np.zeros(3), 0
    for f in frames:
        cam = f.camera()
        v = np.arange(f.height) + 0.5
        _, d = cam.rays(np.stack([np.full_like(v, cam.K[0, 2]), v], 1), normalize=False)  # [H, 3]
        rows = d[:, 2] > 0.05
        if rows.any():
            acc += f.image()[rows].reshape(-1, 3).sum(0)
            n += int(rows.sum()) * f.width
    return (acc / n).astype(np.float32) if n else np.full(3, 0.5, np.float32)


class AppearanceFit:
    """Accumulates (render, alpha, ground truth, camera) frames of the train lanes, then fits
    the colour map on covered pixels and the backgrounds on uncovered ones."""

    def __init__(self, *, covered: float = 0.5, max_pixels: int = 400_000, seed: int = 0):
        self.covered = covered
        self.max_pixels = max_pixels
        self.rng = np.random.default_rng(seed)
        self.pred: list[np.ndarray] = []
        self.target: list[np.ndarray] = []
        self.bg_sum = {True: np.zeros(3), False: np.zeros(3)}
        self.bg_n = {True: 0, False: 0}

    def add(self, render: np.ndarray, alpha: np.ndarray, truth: np.ndarray, cam) -> None:
        cov = alpha >= self.covered
        self.pred.append(render[cov])
        self.target.append(truth[cov])
        up = above_horizon(cam)
        for side in (True, False):
            m = ~cov & (up == side)
            self.bg_sum[side] += truth[m].sum(0)
            self.bg_n[side] += int(m.sum())

    def result(self, default_sky: np.ndarray, default_ground: np.ndarray) -> tuple[ColourMap, Backgrounds]:
        pred = np.concatenate(self.pred) if self.pred else np.zeros((0, 3))
        target = np.concatenate(self.target) if self.target else np.zeros((0, 3))
        if len(pred) > self.max_pixels:
            sel = self.rng.choice(len(pred), self.max_pixels, replace=False)
            pred, target = pred[sel], target[sel]
        cmap = ColourMap.fit(pred, target)
        sky = self.bg_sum[True] / self.bg_n[True] if self.bg_n[True] else np.asarray(default_sky)
        ground = self.bg_sum[False] / self.bg_n[False] if self.bg_n[False] else np.asarray(default_ground)
        return cmap, Backgrounds(np.asarray(sky, np.float32), np.asarray(ground, np.float32))


@dataclass
class Appearance:
    """What a reconstruction method (`mvs`, `gaussians3d`, `sugar`, `nerf`) learned on the train
    split: the colour map and the backgrounds; with none learned, the identity map and the test
    lane's own backgrounds (`background`)."""

    colour_map: ColourMap = field(default_factory=ColourMap)
    backgrounds: Backgrounds | None = None

    def background(self, scene, ground: np.ndarray | None = None) -> Backgrounds:
        """The learned backgrounds, else the lane's own: the sky from its aerial views
        (`sky_colour`), below the horizon `ground` (a colour [3], e.g. the cloud's lowest layer)
        or the sky's."""
        if self.backgrounds is not None:
            return self.backgrounds
        sky = sky_colour(list(scene.aerial))
        return Backgrounds(sky, ground if ground is not None else sky)

    def ground_view(self, colour: np.ndarray, alpha: np.ndarray, scene, cam) -> np.ndarray:
        """A render in the aerial views' colours, colour [H, W, 3] with coverage alpha [H, W], as
        the ground frame [H, W, 3] of `cam`: the colour map on it, composited over the scene's
        backgrounds (`background`; already ground-view colours)."""
        a = alpha[..., None]
        return (self.colour_map(colour) * a + self.background(scene).image(cam) * (1 - a)).astype(np.float32)
