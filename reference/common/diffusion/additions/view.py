"""What an addition may read of one sequence at render time (`SequenceView`): the prior's renders
of its frames, the frames' cameras, the prior's depth and its points (`SceneGeometry`); and the geometry helpers
behind them. Everything here comes from the task's inputs (the aerial views, through the fitted
prior, and the ground poses), never from the ground truth.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from skyeyes_bench.cameras import Camera


def scaled_camera(cam: Camera, width: int, height: int) -> Camera:
    """`cam` with its intrinsics scaled to an image of width x height (the model's square)."""
    K = np.array(cam.K, dtype=np.float64)
    K[0] *= width / cam.width
    K[1] *= height / cam.height
    return Camera(K, cam.c2w, width, height)


def prior_depth(prior, scene, frame, width: int, height: int) -> np.ndarray:
    """The prior's planar depth (m) of its fitted scene (`reference.method.SceneGeometry.depth`)
    seen from `frame`'s pose with its intrinsics scaled to width x height: float64 [height, width],
    +inf where the prior has nothing (the sky and the background)."""
    return prior.depth(scene, scaled_camera(frame.camera(), width, height))


#: Forward-backward consistency of `flow_coords`, pixels at the model's resolution. NOTE: on the
#: `skyeyes-no-vcm` small frames (bench/flow_accuracy.py: the flow between the prior's renders) 1 px
#: kept too little of the picture, 3 px kept the flow's good part (docs/log/skyeyes-2026-11.md).
FLOW_FB_PX = 3.0
#: OpenCV's DIS flow refuses images under this many pixels on both sides.
DIS_MIN_PX = 12


def flow_coords(guides: np.ndarray, *, fb_px: float = FLOW_FB_PX,
                flow: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None
                ) -> Callable[[int], tuple[np.ndarray, np.ndarray]]:
    """j -> (uv, valid) of frame j - 1 seen from frame j, by optical flow between guide images
    [N, H, W, 3] in [0, 1] (OpenCV's DIS flow, Kroeger et al. 2016, on their grey levels): uv the
    pixel centre plus the flow from j to j - 1, valid where it lands inside frame j - 1 and the
    flow back returns within `fb_px` pixels (forward-backward consistency). `flow`: another
    flow, (grey a, grey b) uint8 -> [H, W, 2] with a(x) ~ b(x + flow(x)) (bench/flow_accuracy.py
    compares them)."""
    import cv2

    if flow is None:
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        flow = lambda a, b: dis.calc(a, b, None)  # noqa: E731
    grey = [cv2.cvtColor((np.clip(g, 0, 1) * 255).round().astype(np.uint8), cv2.COLOR_RGB2GRAY) for g in guides]
    h, w = grey[0].shape
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)

    def coords(j: int) -> tuple[np.ndarray, np.ndarray]:
        back = flow(grey[j], grey[j - 1])  # I_j(x) ~ I_{j-1}(x + back(x))
        fwd = flow(grey[j - 1], grey[j])
        uv = np.stack([xs + back[..., 0], ys + back[..., 1]], -1)
        again = cv2.remap(fwd, (uv[..., 0] - 0.5).astype(np.float32), (uv[..., 1] - 0.5).astype(np.float32),
                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        inside = (uv[..., 0] >= 0) & (uv[..., 0] <= w) & (uv[..., 1] >= 0) & (uv[..., 1] <= h)
        return uv, inside & (np.hypot(*(back + again).transpose(2, 0, 1)) <= fb_px)

    return coords


def grid_coords(coords: Callable[[int], tuple[np.ndarray, np.ndarray]], f: int) -> Callable[[int], tuple[np.ndarray, np.ndarray]]:
    """`coords` of an image f times the grid's size -> the same on the grid: each grid pixel
    takes the coordinates (divided by f) and validity of the fine pixel at its centre (f = 1:
    `coords` itself)."""
    if f == 1:
        return coords

    def on_grid(j: int) -> tuple[np.ndarray, np.ndarray]:
        uv, valid = coords(j)
        return uv[f // 2::f, f // 2::f] / f, valid[f // 2::f, f // 2::f]

    return on_grid


def resized_renders(priors: list[np.ndarray], h: int, w: int) -> np.ndarray:
    """The prior's renders of a sequence's frames (its conditions, [H, W, >= 3] each), colour only,
    resized to h x w: [N, h, w, 3] in [0, 1]."""
    from ..core import images_to_tensor, resize_hw

    return resize_hw(images_to_tensor(np.stack(priors)[..., :3]), h, w).permute(0, 2, 3, 1).numpy()


class SequenceView:
    """One sequence of one scene as the additions see it at render time, each part computed once
    per size: the prior's renders (`renders`), the frames' cameras (`cameras`), the prior's depth
    (`depths`: a Gaussian prior's), the prior's Gaussians' means (`means`).

    prior: the prior `Method`, a `reference.method.SceneGeometry` (its depths and points);
    priors: the prior's renders of the sequence's frames, in order (what the ACM is conditioned on)."""

    def __init__(self, prior, scene, sequence, priors: list[np.ndarray]):
        self.prior, self.scene, self.sequence, self.priors = prior, scene, sequence, priors
        self._cache: dict = {}

    def _once(self, key, make):
        if key not in self._cache:
            self._cache[key] = make()
        return self._cache[key]

    def renders(self, h: int, w: int) -> np.ndarray:
        """[N, h, w, 3] in [0, 1]: the prior's renders of the frames."""
        return self._once(("renders", h, w), lambda: resized_renders(self.priors, h, w))

    def cameras(self, h: int, w: int) -> list[Camera]:
        return self._once(("cameras", h, w), lambda: [scaled_camera(f.camera(), w, h) for f in self.sequence.frames])

    def depths(self, h: int, w: int) -> list[np.ndarray]:
        """The prior's planar depth of each frame [h, w] (+inf: nothing of the prior's)."""
        return self._once(("depths", h, w),
                          lambda: [prior_depth(self.prior, self.scene, f, w, h) for f in self.sequence.frames])

    def means(self) -> np.ndarray:
        """[M, 3] the prior's Gaussians' means (world, m)."""
        return self._once("means", lambda: self.prior.points(self.scene))
