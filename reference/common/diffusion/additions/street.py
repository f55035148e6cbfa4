"""The street from one view: after sampling, each frame's pixels of the street take the colour of
one view of that point of the street, the same view whichever frame shows it.

Not in the paper. The road is the one surface whose geometry the method knows to a fraction of a
pixel from the task's inputs: the plane under the prior's Gaussians, placed by the ground poses
(bench/flow_accuracy.py measured 0.42 px median on the near road, where the renders' optical flow
errs by 11 px), so nothing moves by a flow.

Assumption: the street under the cameras is one level plane (world z = const). Checked on every
scene (`level_street`): a plane fitted to the prior's Gaussians under the lane; where it leans
more than `max_tilt_deg`, or the street does not lie on it within `max_rms_m`, this step leaves
the scene's frames as they are (a street that climbs or leans: the synthtown-stiff protocol).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from skyeyes_bench.cameras import Camera
from skyeyes_bench.metrics.geometry import project, sample_bilinear

from .frames import as_frames, blend, hwc
from .view import SequenceView

log = logging.getLogger(__name__)

#: Relative depth tolerance of "not behind the prior's surface" (`street_points`): the prior's
#: alpha-blended depth at edges, wider than the warp metric's 0.01.
DEPTH_TOL = 0.03
#: `street_transfer`'s minification of the owner's view: the Gaussians (px) it chooses from.
_MIP_SIGMAS = (0.0, 0.5, 1.0, 2.0, 4.0)
#: `level_street`: the Gaussians under a lane within this many metres either side of its line.
CORRIDOR_M = 5.0


@dataclass(frozen=True)
class StreetConfig:
    """mix: how far the street's pixels move to their one view's colour (0: off); view_m: the
    owner of a point is the frame that sees it at the planar depth nearest this (m; 0: the
    nearest view); far_m: the street is taken nearer than this (planar depth, m); max_tilt_deg,
    max_rms_m: the level-street check (`level_street`)."""

    mix: float = 0.0
    view_m: float = 4.0
    far_m: float = 30.0
    # NOTE: on the 8 level lanes of synthtown-v2-small-val the prior's Gaussians give a plane
    # 0.14-0.67 degrees off level and the street 0.05-0.06 m off it (the prior's own error;
    # docs/log/skyeyes-2026-11.md), so the check allows 3x that tilt and 4x that spread. 2
    # degrees is a 3.5 % grade: a level plane that far off misplaces the street by 1 m at `far_m`.
    max_tilt_deg: float = 2.0
    max_rms_m: float = 0.25

    def __post_init__(self):
        if not 0.0 <= self.mix <= 1.0 or self.view_m < 0 or self.far_m <= 0 or self.max_tilt_deg <= 0 \
                or self.max_rms_m <= 0:
            raise ValueError(f"street: mix {self.mix} (0..1, 0: off), view_m {self.view_m} (>= 0), far_m "
                             f"{self.far_m}, max_tilt_deg {self.max_tilt_deg}, max_rms_m {self.max_rms_m} (> 0)")


class StreetFromOneView:
    """The street from one view as a step after sampling (`StreetConfig`); `None` from `make` when off."""

    name = "street from one view"
    assumption = "the street under the cameras is one level plane (checked: the prior's Gaussians under the lane)"
    needs_gaussians = True

    def __init__(self, cfg: StreetConfig):
        self.cfg = cfg
        self.levels: dict[str, dict] = {}  # scene -> `level_street`'s finding

    @classmethod
    def make(cls, cfg: StreetConfig) -> "StreetFromOneView | None":
        return cls(cfg) if cfg.mix > 0 else None

    def check(self, view: SequenceView) -> dict:
        """The scene's level-street finding (once a scene): `level_street`'s, with "ground" (the street's
        height the transfer takes, `prior_ground`) and "level" (whether the transfer runs)."""
        name = view.scene.name
        if name not in self.levels:
            centres = np.stack([f.camera().c2w[:3, 3] for f in view.scene.ground])
            found = level_street(view.means(), centres)
            found["ground"] = prior_ground(view.means(), centres[:, 2])  # the transfer's plane
            found["level"] = found["height"] is not None and found["ground"] is not None \
                and found["tilt_deg"] <= self.cfg.max_tilt_deg and found["rms_m"] <= self.cfg.max_rms_m
            if not found["level"]:
                log.info("%s: street from one view steps aside: %s", name, _finding(found, self.cfg))
            self.levels[name] = found
        return self.levels[name]

    def __call__(self, imgs: torch.Tensor, view: SequenceView) -> torch.Tensor:
        found = self.check(view)
        if not found["level"]:
            return imgs
        h, w = imgs.shape[-2:]
        return street_transfer(imgs, view.cameras(h, w), view.depths(h, w), found["ground"], mix=self.cfg.mix,
                               view_m=self.cfg.view_m, far=self.cfg.far_m)


def _finding(found: dict, cfg: StreetConfig) -> str:
    if found["height"] is None or found.get("ground", 0.0) is None:
        return f"too few of the prior's Gaussians under the lane ({found['points']})"
    return (f"a plane through the prior's Gaussians under the lane leans {found['tilt_deg']:.2f} deg (at most "
            f"{cfg.max_tilt_deg}), the street lies {found['rms_m']:.3f} m off it (at most {cfg.max_rms_m})")


def level_street(means: np.ndarray, centres: np.ndarray, *, corridor: float = CORRIDOR_M,
                 min_points: int = 50) -> dict:
    """How level the street under a lane is, from a Gaussian prior's means [M, 3] (world, z up) and
    the lane's ground camera centres [K, 3]: a plane z = a x + b y + c fitted by least squares to
    the means within `corridor` m of the cameras' line (horizontally), below the cameras
    (`street_ceiling` of the nearest camera), refitted twice without the third with the largest
    residuals (cars, kerbs, the underside of the road). Returns {"height": the street's height
    under the cameras' mean (None: fewer than `min_points` means), "tilt_deg": the plane's angle
    to the horizontal, "rms_m": the kept means' RMS distance from it, "points": how many}. The
    street's height for the transfer is `prior_ground`'s, which this does not change."""
    from reference.common.geometry.cloud import MIN_CAMERA_CLEARANCE_M

    xy = centres[:, :2]
    mid = xy.mean(0)
    u = np.linalg.svd(xy - mid)[2][0] if len(xy) > 1 and np.ptp(xy, axis=0).max() > 0 else np.array([1.0, 0.0])
    rel = means[:, :2] - mid
    along, across = rel @ u, rel @ np.array([-u[1], u[0]])
    t = (xy - mid) @ u
    near = np.abs(across) <= corridor
    near &= (along >= t.min() - corridor) & (along <= t.max() + corridor)
    cam_z = np.interp(along, np.sort(t), centres[np.argsort(t), 2])  # the nearest cameras' height
    pts = means[near & (means[:, 2] < cam_z - MIN_CAMERA_CLEARANCE_M)]
    out = {"height": None, "tilt_deg": float("inf"), "rms_m": float("inf"), "points": int(len(pts))}
    if len(pts) < min_points:
        return out
    keep = np.ones(len(pts), dtype=bool)
    for _ in range(3):
        a = np.c_[pts[keep, :2] - mid, np.ones(int(keep.sum()))]
        coef = np.linalg.lstsq(a, pts[keep, 2], rcond=None)[0]
        r = np.abs(np.c_[pts[:, :2] - mid, np.ones(len(pts))] @ coef - pts[:, 2])
        keep = r <= np.quantile(r, 2 / 3)
    rms = float(np.sqrt(np.mean(r[keep] ** 2)))
    return {"height": float(coef[2]), "tilt_deg": float(np.degrees(np.arctan(np.hypot(coef[0], coef[1])))),
            "rms_m": rms, "points": int(len(pts))}


def prior_ground(means: np.ndarray, camera_heights) -> float | None:
    """The street's height (world z, up) under a Gaussian prior's means [M, 3]: `street_height` of
    those under the ground cameras (`street_ceiling`); None where none lie there."""
    from reference.common.geometry.cloud import street_ceiling, street_height

    return street_height(means[:, 2], below=street_ceiling(camera_heights), share=1.0)


def street_points(cam: Camera, depth: np.ndarray, zg: float, *, tol: float = DEPTH_TOL,
                  far: float = 30.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where a frame sees the street, the plane z = zg (world z up), by its camera and the prior's
    planar depth [H, W] (+inf: nothing of the prior's): (points [HW, 3] where the pixels' rays
    meet the plane, their planar depth [HW] (+inf: the ray does not fall), street [HW]: the
    plane nearer than `far` and not behind the prior's surface (its depth, within `tol`, or
    +inf: the prior leaves most of the near road empty, bench/flow_accuracy.py))."""
    o, d = cam.rays(normalize=False)  # camera z = 1: t is planar depth
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (zg - o[:, 2]) / d[:, 2]
    t = np.where((d[:, 2] < 0) & (t > 0), t, np.inf)
    street = (t < far) & (t <= np.asarray(depth, np.float64).ravel() * (1.0 + tol))
    return o + d * np.where(np.isfinite(t), t, 0.0)[:, None], t, street


def _seen(uv: np.ndarray, masks: np.ndarray, h: int, w: int) -> np.ndarray:
    """uv [A, M, 2] in A frames -> [A, M]: within the frame's pixel centres and, at the nearest
    pixel, inside that frame's mask (masks [A, H*W])."""
    with np.errstate(invalid="ignore"):
        inside = (uv[..., 0] >= 0.5) & (uv[..., 0] <= w - 0.5) & (uv[..., 1] >= 0.5) & (uv[..., 1] <= h - 0.5)
    ix = np.clip(np.nan_to_num(uv[..., 0]).astype(np.int64), 0, w - 1)
    iy = np.clip(np.nan_to_num(uv[..., 1]).astype(np.int64), 0, h - 1)
    return inside & np.take_along_axis(masks, iy * w + ix, axis=1)


def _mip(x: np.ndarray, o: int, level: int, cache: dict) -> np.ndarray:
    """Frame o of x [N, H, W, 3] blurred by `_MIP_SIGMAS[level]` (made once per sequence)."""
    from scipy.ndimage import gaussian_filter

    if level == 0:
        return x[o]
    if (o, level) not in cache:
        cache[o, level] = gaussian_filter(x[o], (_MIP_SIGMAS[level], _MIP_SIGMAS[level], 0), mode="nearest")
    return cache[o, level]


def street_transfer(imgs: torch.Tensor, cameras: list[Camera], depths: list[np.ndarray], zg: float, *,
                    mix: float = 1.0, view_m: float = 4.0, tol: float = DEPTH_TOL,
                    far: float = 30.0) -> torch.Tensor:
    """A sequence's decoded frames [N, 3, H, W] in [0, 1] -> the same with the street taken from
    one view of each of its points, so that every frame shows it alike: where a frame sees the
    street (`street_points`), the point takes its colour from the frame that sees it at the
    planar depth nearest `view_m` (the same frame whichever frame asks; 0: the nearest view),
    that view blurred as much as it sees the point nearer (a Gaussian of 0.5 sqrt(s^2 - 1) px for
    s times nearer, the nearest of `_MIP_SIGMAS`). The rest of each frame stays its own. The
    street's pixels move `mix` of the way, half of it on its border pixels.

    cameras: the frames' cameras at H x W (`view.scaled_camera`); depths: the prior's planar
    depths [H, W] (`view.prior_depth`); zg: the street's height (world z, up; `prior_ground`)."""
    if not 0 < mix <= 1 or view_m < 0:
        raise ValueError(f"street_transfer: mix {mix} (0 < mix <= 1), view_m {view_m} (>= 0)")
    n, _, h, w = imgs.shape
    if not (n == len(cameras) == len(depths)):
        raise ValueError(f"street_transfer: {n} frames, {len(cameras)} cameras, {len(depths)} depths")
    x = hwc(imgs)  # [N, H, W, 3]
    parts = [street_points(c, d, zg, tol=tol, far=far) for c, d in zip(cameras, depths)]
    street = np.stack([p[2] for p in parts])  # [N, HW]
    c2ws, ks = np.stack([c.c2w for c in cameras]), np.stack([c.K for c in cameras])
    out, mips = x.copy(), {}
    for k, (pts, _, on) in enumerate(parts):
        target = x[k].reshape(-1, 3).copy()
        idx = np.flatnonzero(on)
        if len(idx):
            uv, z = project(pts[idx], np.ones(len(idx)), c2ws, ks)  # [N, M, 2], [N, M]
            seen = _seen(uv, street, h, w)
            pick = np.abs(z - view_m) if view_m else z
            owner = np.where(seen.any(axis=0), np.argmin(np.where(seen, pick, np.inf), axis=0), -1)
            scale = z[k] / np.take_along_axis(z, np.maximum(owner, 0)[None], 0)[0]
            want = 0.5 * np.sqrt(np.maximum(scale ** 2 - 1.0, 0.0))
            level = np.abs(want[:, None] - np.asarray(_MIP_SIGMAS)[None]).argmin(1)
            for o in np.unique(owner[owner >= 0]):  # -1: no frame sees it within its pixel centres
                for lv in np.unique(level[owner == o]):
                    sel = (owner == o) & (level == lv)
                    target[idx[sel]] = sample_bilinear(_mip(x, o, lv, mips), uv[o, sel])
        out[k] = blend(x[k], target.reshape(h, w, 3), on.reshape(h, w), mix)
    return as_frames(out, imgs)
