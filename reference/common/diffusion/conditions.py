"""What conditions a diffusion model: per ground frame an image [H, W, C] in [0, 1] (C = 3, or
more for a condition with extra channels, `CoreConfig.cond_extra`), the part of the pipeline in
which the family's members differ most (`pipeline.DiffusionMethod.make_condition`).

- `PriorRenders`: another method's renders of every ground pose (Skyeyes' Gaussian prior, SuGaR;
  gvg's `mvs` geometry), cached by content hash (`reference.common.priors.render_priors`); that
  method sees the aerial views and the ground *poses* only.
- `NearestAerial`: the aerial view whose camera is nearest the ground camera (controlnet, ip2p).

Both are parts of the method that fit on the test scenes at once (`Method.scene_parts`): their
`fit_scenes` keeps the scenes' conditions, which `of_scene` hands to the method's per-scene fit.
`PriorFits` is the part that keeps the prior's fitted scenes, whose depth and Gaussians the
additions read (`additions`: the street and the sky).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import numpy as np

from reference.common.priors import frame_key, nearest_aerial, render_priors

if TYPE_CHECKING:
    from reference.method import Method
    from skyeyes_bench.data.layout import Dataset, Scene


class SceneConditions:
    """The conditions of the scenes `fit_scenes` saw, kept for `of_scene`."""

    def __init__(self):
        self.kept: dict[str, np.ndarray] = {}

    def images(self, dataset: "Dataset | None", scenes: list["Scene"], *, progress: bool,
               jobs: int) -> tuple[dict[str, np.ndarray], float]:
        raise NotImplementedError

    def fit_scenes(self, scenes: list["Scene"], *, progress: bool, jobs: int) -> float:
        """Keep the conditions of `scenes` (test scenes: no dataset); return the seconds taken
        from caches."""
        conds, cached_s = self.images(None, scenes, progress=progress, jobs=jobs)
        self.kept.update(conds)
        return cached_s

    def of_scene(self, scene: "Scene") -> dict[str, np.ndarray]:
        """{frame key: condition} of the ground frames of `scene`, which `fit_scenes` saw."""
        return {frame_key(scene, f): self.kept[frame_key(scene, f)] for f in scene.ground}


class NearestAerial(SceneConditions):
    """Each ground frame's nearest aerial view (`priors.nearest_aerial`): nothing to fit."""

    def images(self, dataset: "Dataset | None", scenes: list["Scene"], *, progress: bool,
               jobs: int) -> tuple[dict[str, np.ndarray], float]:
        """({frame key: the image}, seconds taken from caches: none)."""
        return {frame_key(s, f): nearest_aerial(s, f).image() for s in scenes for f in s.ground}, 0.0


class PriorRenders(SceneConditions):
    """The renders of a prior method at every ground pose, optionally re-encoded per frame
    (`encode`: gvg's colour, depth and coverage -> its condition channels).

    Args:
        prior: returns the prior method (built when first asked for).
        encode: float32 [H, W, C] render -> the condition [H, W, C'] (None: the render).
    """

    def __init__(self, prior: Callable[[], "Method"], encode: Callable[[np.ndarray], np.ndarray] | None = None):
        super().__init__()
        self.prior, self.encode = prior, encode

    def images(self, dataset: "Dataset | None", scenes: list["Scene"], *, progress: bool,
               jobs: int) -> tuple[dict[str, np.ndarray], float]:
        """({frame key: the condition}, the original seconds of the renders and fits taken from
        caches): the prior fitted per scene `jobs` at a time and rendered (`render_priors`)."""
        conds, cached_s = render_priors(dataset, scenes, self.prior(), progress=progress, jobs=jobs)
        if self.encode is not None:
            conds = {k: self.encode(v) for k, v in conds.items()}
        return conds, cached_s


class PriorFits:
    """The prior's fitted scenes, for its depth and Gaussians (`additions`): fitted `jobs` at a time, those
    `PriorRenders` left unfitted (their renders came from the cache)."""

    def __init__(self, prior: Callable[[], "Method"]):
        self.prior = prior

    def fit_scenes(self, scenes: list["Scene"], *, progress: bool, jobs: int) -> float:
        """Fit the prior on `scenes` it has not fitted; its seconds taken from caches."""
        prior = self.prior()
        before = prior.cached_s
        prior.fit_scenes([s for s in scenes if not prior.has_fitted(s)])
        return prior.cached_s - before
