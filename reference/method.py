"""The one life cycle of a reference method, driven by `reference.reproduce` (and by the bench
scripts, and by a method run inside another, as Skyeyes runs its prior).

1. Config: `Method.configure(preset, sets)` is the preset's config dataclass with `--set
   KEY=VALUE` overrides (typed and checked against its fields; a dotted key sets a field of a
   nested config), plus the device and a pretrained model when asked for. `from_preset` builds
   a method from it. Configs are saved with every run so a run can be repeated from its output.
2. `fit_train(dataset)`: learn what carries across scenes from the *train* split (a diffusion
   model, a colour map). Optional; methods that only reconstruct a scene leave it empty.
3. `fit_scenes(scenes)`: per test scene (a lane). Only the scene's aerial images and poses may
   be used, plus the *poses and intrinsics* of its ground cameras (never their pixels). A
   method's one hook here is `fit_scene_model(scene)`; the base class resumes each scene from
   its checkpoint (`scene_checkpoint`) or calls the hook and saves what it returns, in worker
   processes where the method allows it (`parallel_scenes`). Parts a method is assembled from
   that fit on every scene at once (a diffusion model's prior renders: `scene_parts`) fit first.
4. `render_sequence(scene, sequence)`: yield one float32 [H, W, 3] image in [0, 1] per ground
   frame of the sequence, in order (by default `render_frame` of each frame).

Around these, the same for every method:

- the cache key of a run (`cache_key`: method, version, config, seed, dataset, `code_sha`);
- checkpoints (`checkpointed`): one resume rule, writes through a temporary file renamed into
  place (a killed run never leaves half a checkpoint), statistics beside each in a JSON file;
- timing: `cached_s`, the original seconds of the work an instance took from caches (resumed
  checkpoints, cached stages and priors), so a run reports what producing its result cost. It
  changes in one place: `took_from_cache` counts such seconds (every cache, and every method run
  inside another, reports through it), `uncounted` leaves out a block's (work a worker process
  did in this run);
- per-scene statistics (`scene_stats`, each scene's fit.json) and the device (`device`).
"""

from __future__ import annotations

import abc
import contextlib
import dataclasses
import hashlib
import inspect
import json
import logging
import time
from pathlib import Path
from typing import Any, Callable, ClassVar, Iterator, Protocol, TypeVar

import numpy as np

from skyeyes_bench import inputfiles, outputfiles
from skyeyes_bench.data.layout import Dataset, Frame, Scene, Sequence
from skyeyes_bench.errors import UserError

T = TypeVar("T")

# --------------------------------------------------------------------------- config


def parse_overrides(config, items: list[str], _prefix: str = "") -> dict:
    """["iterations=200", "sfm=false", "core.residual=false"] -> typed dict, checked against the
    config's fields; a dotted key sets a field of a nested config (the whole nested config is
    replaced, with its other fields kept)."""
    fields = {f.name: f for f in dataclasses.fields(config)}
    out = {}
    nested: dict[str, list[str]] = {}
    for item in items:
        key, eq, raw = item.partition("=")
        if not eq:
            raise UserError(f"--set {item!r}: expected KEY=VALUE")
        head, dot, rest = key.partition(".")
        if dot and head in fields and dataclasses.is_dataclass(getattr(config, head)):
            nested.setdefault(head, []).append(f"{rest}={raw}")
            continue
        if key not in fields:
            raise UserError(f"--set {_prefix}{key}: not a field of {type(config).__name__} (fields: {', '.join(fields)})")
        cur = getattr(config, key)
        try:
            if isinstance(cur, bool):
                if raw.lower() not in ("true", "false", "1", "0", "yes", "no"):
                    raise ValueError
                val = raw.lower() in ("true", "1", "yes")
            elif isinstance(cur, int):
                val = int(raw)
            elif isinstance(cur, float):
                val = float(raw)
            else:
                val = type(cur)(raw) if cur is not None else raw
        except ValueError:
            raise UserError(f"--set {_prefix}{key}={raw}: expected a {type(cur).__name__}") from None
        out[key] = val
    for head, sub_items in nested.items():
        sub = out.get(head, getattr(config, head))
        try:
            out[head] = dataclasses.replace(sub, **parse_overrides(sub, sub_items, f"{_prefix}{head}."))
        except ValueError as e:  # the nested config's own validation
            raise UserError(f"--set {head}.*: {e}") from None
    return out


def has_field(config: Any, name: str) -> bool:
    """Whether the config dataclass `config` has a field `name`."""
    return dataclasses.is_dataclass(config) and any(f.name == name for f in dataclasses.fields(config))


# --------------------------------------------------------------------------- cache keys


def json_sha(obj: Any) -> str:
    """sha256 (hex) of `obj` as canonical JSON (sorted keys; what JSON cannot hold as its str)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def code_sha(cls, skip: tuple[str, ...] = ()) -> str:
    """sha256 of the method's modules (its class hierarchy) and of reference/common, less the
    packages of reference/common named in `skip` (ones the method never imports)."""
    files = {Path(inspect.getfile(c)).resolve() for c in inspect.getmro(cls) if c.__module__.startswith("reference")}
    common = Path(__file__).resolve().parent / "common"
    files |= {f for f in common.rglob("*.py") if f.relative_to(common).parts[0] not in skip}
    h = hashlib.sha256()
    for f in sorted(files):
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def cache_key(method: str, version: str, config: dict, seed: int, data_sha: str, code: str) -> str:
    """The key of a run's stage cache: everything its outputs depend on."""
    return json_sha({"method": method, "version": version, "config": config, "seed": seed, "data": data_sha,
                     "code": code})[:16]


# --------------------------------------------------------------------------- the method


class SceneGeometry(Protocol):
    """What a prior offers of a fitted scene's geometry to what conditions on it (the diffusion
    family's additions), instead of its internals (`reference.common.gaussians.scene_geometry`)."""

    def depth(self, scene: Scene, cam) -> np.ndarray:
        """Planar depth (m) seen by `cam` (a `skyeyes_bench.cameras.Camera`): float64
        [cam.height, cam.width], +inf where the scene has nothing."""
        ...

    def points(self, scene: Scene) -> np.ndarray:
        """[M, 3] points of the fitted scene (world, m, z up)."""
        ...


class SceneParts(Protocol):
    """A part of a method that fits on many scenes at once, before the method's own per-scene
    fits (`Method.scene_parts`)."""

    def fit_scenes(self, scenes: list[Scene], *, progress: bool, jobs: int) -> float:
        """Fit on `scenes`; return the original seconds of the work taken from caches."""
        ...


class Method(abc.ABC):
    name: ClassVar[str]
    version: ClassVar[str] = "0.1"
    #: preset name -> config dataclass instance
    presets: ClassVar[dict[str, Any]]
    #: File in `scene_dir(scene)` that holds a fitted scene (`save_scene_model`); None: what
    #: `fit_scene_model` returns is not saved, the hook runs again in every run.
    scene_checkpoint: ClassVar[str | None] = None
    #: What the method is to the board (`skyeyes_bench.leaderboard.kinds`): "paper" (the paper's
    #: method), "ablation" (the paper's ablation), "baseline" (a baseline the paper compares
    #: with), "floor", or "beyond" (not in the paper).
    kind: ClassVar[str] = "beyond"

    def __init__(self, config: Any, workdir: Path, *, seed: int = 0, progress: bool = True):
        self.config = config
        self.workdir = Path(workdir)
        self.seed = seed
        self.progress = progress  # progress bars of the method's own stages
        #: Per fitted scene, what its fit reported (`fit_seconds` and the method's own numbers;
        #: saved as the scene's fit.json).
        self.scene_stats: dict[str, dict] = {}
        self._cached_s = 0.0  # `cached_s`: changed by `took_from_cache` and `uncounted` alone
        #: Worker processes for fits of several scenes (`reference.parallel.fit_scenes`): a run
        #: option (`reproduce --jobs`), not config, since it changes run time and never results.
        self.jobs = 1
        self._scene_models: dict[str, Any] = {}
        self.workdir.mkdir(parents=True, exist_ok=True)

    # ---------------------------------------------------------------- time accounting
    @property
    def cached_s(self) -> float:
        """Original seconds of the work this instance took from caches instead of doing it
        (resumed checkpoints, cached stages and priors, what a method run inside it took): a run
        reports its wall time plus this."""
        return self._cached_s

    def took_from_cache(self, seconds: float) -> None:
        """Count `seconds`, the original cost of work taken from a cache instead of done (a
        resumed checkpoint, a cached stage or prior, another method's `cached_s`), into
        `cached_s`; negative to take back seconds counted twice."""
        self._cached_s += seconds

    @contextlib.contextmanager
    def uncounted(self) -> Iterator[None]:
        """Within the block, what is taken from caches does not count: work this run did itself
        elsewhere (a worker process fitted the scene now; its time is in the caller's clock)."""
        before = self._cached_s
        try:
            yield
        finally:
            self._cached_s = before

    # ---------------------------------------------------------------- config
    @classmethod
    def configure(cls, preset: str, sets: list[str] | tuple = (), *, values: dict | None = None,
                  device: str | None = None, pretrained: str | None = None) -> tuple[Any, list[str]]:
        """The config of `preset` with its overrides, and those overrides as the `KEY=VALUE`
        strings that repeat the run.

        Args:
            sets: `--set` strings, applied in order ("iterations=200", "core.residual=false").
            values: typed field values, for callers in code (not in the returned strings).
            device: the torch device (a UserError for a CPU-only method, unless "cpu").
            pretrained: a local diffusers Stable Diffusion folder (the diffusion methods).
        """
        from skyeyes_bench.registry import lookup

        base = lookup(cls.presets, preset, f"preset of method {cls.name!r}")
        applied = list(sets)
        config = dataclasses.replace(base, **{**parse_overrides(base, applied), **(values or {})})
        if device is not None:
            from skyeyes_bench.devices import resolve_device

            resolve_device(device)  # a device this machine lacks: one line, before any work
            if has_field(config, "device"):
                config = dataclasses.replace(config, device=device)
                applied.append(f"device={device}")
            elif device != "cpu":
                raise UserError(f"--device {device}: method {cls.name!r} runs on the CPU only "
                                "(its config has no device)")
        if pretrained is not None:
            if not has_field(config, "pretrained"):
                raise UserError(f"--pretrained: method {cls.name!r} takes no pretrained model "
                                "(only the diffusion methods do)")
            root = Path(pretrained).expanduser().resolve()
            if not (root / "unet" / "config.json").is_file():
                raise UserError(f"--pretrained {pretrained}: not a diffusers Stable Diffusion folder "
                                "(expected unet/config.json)")
            config = dataclasses.replace(config, pretrained=str(root))
            applied.append(f"pretrained={root}")
        return config, applied

    @classmethod
    def from_preset(cls, preset: str, workdir: Path, *, seed: int = 0, progress: bool = True, **values) -> "Method":
        """The method with the config of `preset`, fields in `values` replaced."""
        config, _ = cls.configure(preset, values=values)
        return cls(config, workdir, seed=seed, progress=progress)

    def config_dict(self) -> dict:
        return dataclasses.asdict(self.config)

    def components(self) -> list[str]:
        """Every part the method runs, in words and in order (the board lists them with its
        row); the method's own description by default."""
        doc = (type(self).__doc__ or "").strip().split("\n\n")[0]
        return [" ".join(doc.split())] if doc else []

    @property
    def device(self) -> str:
        """The config's torch device, resolved where every device is (`skyeyes_bench.devices`:
        "auto" is CUDA when available, else the CPU); "cpu" for a config without one."""
        from skyeyes_bench.devices import device_name

        return device_name(getattr(self.config, "device", "cpu"), what="device")

    def use_threads(self) -> None:
        """The config's torch intra-op threads (`threads`; 0: every core), set before each stage
        because a stage run inside another leaves its own setting behind. None: left as is."""
        n = getattr(self.config, "threads", None)
        if n is not None:
            from skyeyes_bench.threads import set_threads

            set_threads(n)

    # ---------------------------------------------------------------- checkpoints
    @property
    def train_dir(self) -> Path:
        """Where a method keeps what it learned on the train split."""
        return self.workdir / "train"

    def scene_dir(self, scene: Scene) -> Path:
        """Where a method keeps what it fitted on `scene` (its checkpoint and fit.json)."""
        return self.workdir / "scenes" / scene.name

    def checkpointed(self, path: Path, compute: Callable[[], tuple[T, dict]], *, save: Callable[[T, Path], None],
                     load: Callable[[Path], T], stats: Path, seconds: str = "seconds") -> tuple[T, dict]:
        """Resume from the checkpoint `path`, or compute and save it: the one rule of every method.

        A checkpoint exists only complete: `stats` (JSON) is written first, then `save(value,
        tmp)` writes a temporary file beside `path` that is renamed to `path`. So when `path`
        exists, `(load(path), the stats)` is returned, and the seconds the stats record
        (`stats[seconds]`) are added to `cached_s`. Otherwise `compute()` returns `(value,
        stats)`, its wall time goes into `stats[seconds]`, and both are saved.
        """
        path = Path(path)
        if path.is_file():
            value = load(path)
            recorded = inputfiles.read_json(stats, allow_nan=True) if Path(stats).is_file() else {}
            self.took_from_cache(float(recorded.get(seconds, 0.0)))
            logging.getLogger(type(self).__module__).info("reusing %s", path)
            return value, recorded
        t0 = time.perf_counter()
        value, info = compute()
        info[seconds] = time.perf_counter() - t0
        outputfiles.write_json(stats, info)
        with outputfiles.atomic_path(path) as tmp:
            save(value, tmp)
        return value, info

    # ---------------------------------------------------------------- the life cycle
    def fit_train(self, dataset: Dataset) -> None:  # noqa: B027  (optional hook)
        """Learn from the train split. Default: nothing to learn across scenes."""

    def fit_scenes(self, scenes: list[Scene], *, progress: bool | None = None) -> None:
        """Fit every scene of `scenes`: first the method's `scene_parts`, on all of them at once,
        then `fit_one_scene` of each, `self.jobs` at a time in worker processes where
        `parallel_scenes` allows it (`reference.parallel`); the same result as in turn."""
        from reference.parallel import fit_scenes

        progress = self.progress if progress is None else progress
        for part in self.scene_parts():
            self.took_from_cache(part.fit_scenes(scenes, progress=progress, jobs=self.jobs))
        fit_scenes(self, scenes, jobs=self.jobs, progress=progress)

    def fit_scene(self, scene: Scene, *, progress: bool | None = None) -> None:
        """`fit_scenes` of one scene."""
        self.fit_scenes([scene], progress=progress)

    def fit_one_scene(self, scene: Scene, *, progress: bool) -> None:
        """One scene's step of `fit_scenes` (what a worker process runs): resume it from
        `scene_dir(scene)/scene_checkpoint`, or `fit_scene_model` it (and save that when the
        method has a checkpoint). The parts must have fitted already."""
        self.use_threads()
        if self.scene_checkpoint is None:
            model, stats = self.fit_scene_model(scene, progress=progress)
        else:
            folder = self.scene_dir(scene)
            model, stats = self.checkpointed(folder / self.scene_checkpoint,
                                             lambda: self.fit_scene_model(scene, progress=progress),
                                             save=self.save_scene_model, load=self.load_scene_model,
                                             stats=folder / "fit.json", seconds="fit_seconds")
        self._scene_models[scene.name] = model
        self.scene_stats[scene.name] = stats

    def scene_parts(self) -> list[SceneParts]:
        """Parts of the method that fit on every test scene before its own per-scene fits, all
        scenes at once (the diffusion family's conditions: `reference.common.diffusion`). None
        by default."""
        return []

    @property
    def parallel_scenes(self) -> bool:
        """Whether `fit_scenes` may fit this method's scenes in worker processes (`--jobs`): it
        keeps a checkpoint per scene to hand back, and fits on one torch thread (more would
        oversubscribe the cores). A method may say otherwise."""
        return self.scene_checkpoint is not None and getattr(self.config, "threads", None) == 1

    def fit_scene_model(self, scene: Scene, *, progress: bool) -> tuple[Any, dict]:
        """The hook of the per-scene fit: fit `scene` from scratch, return (what
        `save_scene_model` saves, or what rendering needs; the fit's statistics)."""
        raise NotImplementedError(f"{self.name}: fit_scene_model is not its own")

    def save_scene_model(self, model: Any, path: Path) -> None:
        """Write a fitted scene to `path` (a temporary file that is then renamed)."""
        raise NotImplementedError

    def load_scene_model(self, path: Path) -> Any:
        """Read back what `save_scene_model` wrote; equal to what was saved, bit for bit."""
        raise NotImplementedError

    def has_fitted(self, scene: Scene) -> bool:
        """Whether `scene` was fitted (or resumed) in this run."""
        return scene.name in self._scene_models

    def scene_model(self, scene: Scene) -> Any:
        """What `fit_scene_model` fitted on (or resumed for) `scene`."""
        if scene.name not in self._scene_models:
            raise RuntimeError(f"{self.name}: {scene.name} rendered before fit_scene")
        return self._scene_models[scene.name]

    def render_sequence(self, scene: Scene, sequence: Sequence) -> Iterator[np.ndarray]:
        """Yield float32 [H, W, 3] images in [0, 1], one per frame of `sequence`, in order. By
        default `render_frame` of each frame, on the config's threads."""
        self.use_threads()
        for frame in sequence:
            yield self.render_frame(scene, frame)

    def render_frame(self, scene: Scene, frame: Frame) -> np.ndarray:
        """One ground frame of a fitted scene, float32 [H, W, 3] in [0, 1]: what a method that
        renders frame by frame defines instead of `render_sequence`."""
        raise NotImplementedError(f"{self.name}: neither render_sequence nor render_frame is its own")
