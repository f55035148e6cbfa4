"""The per-frame conditions of the diffusion methods: a prior's renders of every ground pose
(Skyeyes' Gaussian prior), cached by content hash; or the nearest aerial view (the ControlNet
baseline).

A prior is a part of `reference/common` (`PRIOR_PARTS`), named by the diffusion config's
`prior_method`: the same parts the `sugar`, `gaussians3d` and `mvs` rows are made of, never a
method looked up by its id.
"""

from __future__ import annotations

import hashlib
import time
from typing import TYPE_CHECKING

import numpy as np

from skyeyes_bench import imagefiles, inputfiles, outputfiles
from skyeyes_bench.data.layout import Dataset, Frame, Scene
from skyeyes_bench.paths import cache_dir

if TYPE_CHECKING:
    from reference.method import Method

#: The priors a diffusion method may condition on, by the name its config gives (`prior_method`):
#: "module:Class" of a part (a `Method` of `reference/common`), loaded when first used.
PRIOR_PARTS: dict[str, str] = {
    "sugar": "reference.common.sugar:SuGaRSplatting",
    "gaussians3d": "reference.common.splatting:GaussianSplatting",
    "mvs": "reference.common.mvs_cloud:MVSCloud",
}
#: The priors made of Gaussians, whose depth and means the additions read (`additions.view`).
GAUSSIAN_PRIORS = ("sugar", "gaussians3d")


def prior_part(name: str, preset: str, workdir, seed: int, device: str | None = None, **values) -> "Method":
    """The prior `name` of `PRIOR_PARTS` at `preset` (config fields in `values` replaced), on
    `device` when its config has one; a name not there is a one-line UserError listing them."""
    from reference.method import has_field
    from skyeyes_bench.registry import load_entry_point, lookup

    cls = load_entry_point(lookup(PRIOR_PARTS, name, "prior"))
    extra = {"device": device} if device is not None and has_field(cls.presets[preset], "device") else {}
    return cls.from_preset(preset, workdir, seed=seed, **values, **extra)


#: Key of a prior cache entry holding the seconds it cost (frame keys are relative file paths).
_SECONDS = "_seconds"


def frame_key(scene: Scene, frame: Frame) -> str:
    return f"{scene.name}/{frame.file}"


def scene_aerial_hash(scene: Scene) -> str:
    """Content hash of what a prior may use: scene.json (poses, intrinsics) and aerial pixels."""
    h = hashlib.sha256((scene.root / "scene.json").read_bytes())
    for f in scene.aerial:
        h.update(inputfiles.sha256_file(f.path).encode())
    return h.hexdigest()


def render_priors(dataset: Dataset, scenes: list[Scene], prior_method: Method, *,
                  progress: bool = True, jobs: int = 1) -> tuple[dict[str, np.ndarray], float]:
    """Fit `prior_method` per scene and render every ground pose.

    The prior sees a scene through `fit_scenes` (aerial views and ground *poses* only) and
    `render_sequence`; renders are cached by (method, config, seed, code, scene content) hash under
    `<cache>/reference/priors/`, each entry with the seconds producing it cost (the scene's fit,
    as its fit.json records it, plus the renders). Scenes not in the cache are fitted `jobs` at a
    time in worker processes (`reference.parallel.fit_scenes`), then rendered here.

    Returns:
        ({"<scene>/<frame file>": float32 [H, W, C]} for every ground frame (C = 3: colour in
        [0, 1], quantised to 8 bits as a PNG would be; renders with more channels are kept as
        float32), the
        original seconds of the work taken from caches: entries of this cache, and prior fits
        resumed from their checkpoints).
    """
    from tqdm import tqdm

    from reference.method import code_sha, json_sha
    from reference.parallel import fit_scenes

    out: dict[str, np.ndarray] = {}
    cached_s = 0.0
    # The prior's code is part of the key: renders cached by an older `sugar` (or the `mvs` cloud
    # it starts from) are not this code's priors. The diffusion package is left out: priors
    # never import it, and its changes would otherwise re-fit every prior.
    ident = {"method": prior_method.name, "version": prior_method.version,
             "config": prior_method.config_dict(), "seed": prior_method.seed,
             "code": code_sha(type(prior_method), skip=("diffusion",))}
    paths = {scene.name: cache_dir() / "reference" / "priors"
             / f"{scene.name}-{json_sha({**ident, 'scene': scene_aerial_hash(scene)})[:24]}.npz" for scene in scenes}
    todo = [scene for scene in scenes if not paths[scene.name].is_file()]
    before = prior_method.cached_s
    fit_scenes(prior_method, todo, jobs=jobs, progress=progress)  # the prior's fit bars obey ours
    cached_s += prior_method.cached_s - before  # fits resumed from checkpoints: their first run's time
    for scene in tqdm(scenes, desc="priors", disable=None if progress else True, leave=False):
        path = paths[scene.name]
        if path.is_file():
            with np.load(path) as z:
                for f in scene.ground:
                    out[frame_key(scene, f)] = _from_stored(z[f.file])
                cached_s += float(z[_SECONDS]) if _SECONDS in z.files else 0.0  # older caches: unknown
            continue
        t0 = time.perf_counter()
        rendered: dict[str, np.ndarray] = {}
        for seq in scene.sequences.values():
            for frame, img in zip(seq.frames, prior_method.render_sequence(scene, seq), strict=True):
                rendered[frame.file] = _to_stored(np.asarray(img))
        fit_s = float(prior_method.scene_stats.get(scene.name, {}).get("fit_seconds", 0.0))
        seconds = np.float64(fit_s + time.perf_counter() - t0)  # what producing this entry cost
        with outputfiles.atomic_path(path, suffix=".npz") as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, **rendered, **{_SECONDS: seconds})
        out.update({f"{scene.name}/{k}": _from_stored(v) for k, v in rendered.items()})
    return out, cached_s


def _to_stored(img: np.ndarray) -> np.ndarray:
    """A render as its cache entry stores it: 8-bit for colour images [H, W, 3] (what a PNG
    would hold), float32 for renders with more channels (gvg's depth and coverage beside the
    colour), which 8 bits would quantise."""
    return imagefiles.to_uint8(img) if img.shape[-1] == 3 else img.astype(np.float32)


def _from_stored(a: np.ndarray) -> np.ndarray:
    """Inverse of `_to_stored`: float32 [H, W, C]."""
    return a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a.astype(np.float32)


def nearest_aerial(scene: Scene, frame: Frame) -> Frame:
    """The aerial view whose camera centre is nearest the ground camera's (the ControlNet
    baseline's condition)."""
    centres = np.stack([a.c2w[:3, 3] for a in scene.aerial])  # [A, 3]
    return scene.aerial[int(np.argmin(np.linalg.norm(centres - frame.c2w[:3, 3], axis=1)))]
