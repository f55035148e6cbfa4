"""Scene-parallel fits: the scenes of a method fitted in worker processes at once.

The geometry methods (`mvs`, `gaussians3d`, `sugar`, `nerf`, and `sugar` as Skyeyes' prior) fit
each lane on one torch thread (a second OpenMP thread only spins on this shared 2-core machine:
`Gaussians3DConfig.threads`), so one process leaves the other cores idle. Lanes are independent
(each fit seeds itself from the method's seed, never from a previous lane), so `jobs` worker
processes fit `jobs` lanes at a time and the result is the same, bit for bit, as fitting them in
turn: each worker runs the method's `fit_one_scene`, which writes the lane's checkpoint through
a temporary file; the calling process then loads every checkpoint as a resumed fit would.

With `reproduce --ray` (`on_ray`) the same worker function runs as Ray tasks instead (one CPU
each, a share of a GPU for a method on CUDA), placed by the cluster (`skyeyes_bench.ray_exec`;
the method's work folder, under --out, and the dataset must lie on a path every worker sees); the
checkpoints they write are loaded here as above, so the results are again those of fits in turn.

Timing stays honest: the seconds a loaded checkpoint records are added to `cached_s` only for
lanes fitted by an earlier run (the original cost of work taken from a cache); lanes the workers
fitted now are in the caller's wall clock already.
"""

from __future__ import annotations

import contextlib
import contextvars
import logging
import os
import pickle
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path
from typing import TYPE_CHECKING, Iterator, Protocol

if TYPE_CHECKING:
    from skyeyes_bench.data.layout import Scene

log = logging.getLogger(__name__)


class SceneFitter(Protocol):
    """What the fits here need of a method (`reference.method.Method` is one; this module does not
    import it, so the method module can call on this one without an import circle)."""

    name: str
    device: str
    scene_checkpoint: str | None
    progress: bool
    cached_s: float

    @property
    def parallel_scenes(self) -> bool: ...

    def fit_one_scene(self, scene: "Scene", *, progress: bool) -> None: ...

    def uncounted(self) -> contextlib.AbstractContextManager: ...

    def scene_dir(self, scene: "Scene") -> Path: ...

#: The most worker processes that ran at once in this process (for the peak memory of a run).
_most_workers = 0


def most_workers() -> int:
    """The largest number of worker processes `fit_scenes` ran at once in this process."""
    return _most_workers


def available_cores() -> int:
    """CPU cores this process may run on (the affinity mask, else os.cpu_count())."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # not on Linux
        return max(os.cpu_count() or 1, 1)


#: Lanes fitted at once on one GPU: each worker process holds its own CUDA context (~0.5 GB) and
#: a lane's splats (well under 1 GB at `small`); the lanes' many small kernels overlap. NOTE: not
#: yet measured on a GPU (docs/gpu.md); `--jobs N` overrides it.
GPU_LANES = 8


def default_jobs(method: SceneFitter) -> int:
    """Worker processes when the user did not say: every core for a method on the CPU, up to
    `GPU_LANES` (and the cores) on a GPU, else 1. `fit_scenes` uses them only for methods that
    allow it (`Method.parallel_scenes`)."""
    device = method.device
    if device == "cpu":
        return available_cores()
    if device.startswith("cuda"):
        return min(available_cores(), GPU_LANES)
    return 1


class _Keep(logging.Handler):
    """Collects a worker's log records, made picklable, to be handled again by the caller."""

    def __init__(self):
        super().__init__(logging.INFO)
        self.setFormatter(logging.Formatter())
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        record.msg, record.args = record.getMessage(), None
        record.exc_text = self.formatter.formatException(record.exc_info) if record.exc_info else record.exc_text
        record.exc_info = None
        self.records.append(record)


def _fit_one(method: SceneFitter, scene: "Scene") -> list[logging.LogRecord]:
    """Worker: fit one scene with the caller's method (its train-split state included); return
    the log records it made (the caller's log gets them). The checkpoint, with the fit's
    statistics beside it, is on disk when this returns."""
    keep = _Keep()
    root = logging.getLogger()
    root.addHandler(keep)
    root.setLevel(logging.INFO)
    method.progress = False
    method.fit_one_scene(scene, progress=False)
    return keep.records


#: Whether `fit_scenes` runs its workers as Ray tasks (`on_ray`) rather than local processes.
_ON_RAY: contextvars.ContextVar[bool] = contextvars.ContextVar("reference_fits_on_ray", default=False)


@contextlib.contextmanager
def on_ray() -> Iterator[None]:
    """Within the block, `fit_scenes` fits scenes as tasks of the running Ray (`ray_exec.session`),
    whatever `jobs` says: the cluster's resources decide how many run at once."""
    token = _ON_RAY.set(True)
    try:
        yield
    finally:
        _ON_RAY.reset(token)


def _in_workers(method: SceneFitter, todo: list["Scene"], jobs: int) -> Iterator[list[logging.LogRecord]]:
    """`_fit_one` for each scene of `todo` in `jobs` local worker processes, or as Ray tasks
    (`on_ray`); yields each fit's log records as it completes (a worker's exception is raised)."""
    if _ON_RAY.get():
        from skyeyes_bench import ray_exec

        gpus = 1 / GPU_LANES if method.device.startswith("cuda") else 0
        log.info("%s: fitting %d scenes as Ray tasks", method.name, len(todo))
        yield from ray_exec.map_unordered(_fit_one, [(method, s) for s in todo], num_cpus=1, num_gpus=gpus)
        return
    n = min(jobs, len(todo))
    global _most_workers
    _most_workers = max(_most_workers, n)
    log.info("%s: fitting %d scenes in %d worker processes", method.name, len(todo), n)
    # spawn, not fork: torch's thread pools do not survive a fork.
    with ProcessPoolExecutor(n, mp_context=get_context("spawn")) as pool:
        for fut in as_completed([pool.submit(_fit_one, method, s) for s in todo]):
            yield fut.result()  # a worker's exception is raised here, with its traceback


def fit_scenes(method: SceneFitter, scenes: list["Scene"], *, jobs: int = 1, progress: bool = True) -> None:
    """`method.fit_one_scene` for every scene, `jobs` scenes at a time in worker processes
    where the method allows it (`parallel_scenes`; 1: in this process, in turn). Afterwards
    every scene is fitted in `method` as `fit_one_scene` leaves it, and `method.cached_s` counts
    only work earlier runs did."""
    todo = []
    if (jobs > 1 or _ON_RAY.get()) and method.parallel_scenes:
        todo = [s for s in scenes if not (method.scene_dir(s) / method.scene_checkpoint).is_file()]
    if len(todo) > 1:
        try:
            pickle.dumps(method)
        except Exception as err:  # noqa: BLE001  (any pickling failure: fall back, say why)
            log.warning("%s: scenes fitted in turn, not in %d processes: the method does not pickle (%s)",
                        method.name, jobs, err)
            todo = []
    fresh: set[str] = set()
    if len(todo) > 1:
        from tqdm import tqdm

        for records in tqdm(_in_workers(method, todo, jobs), total=len(todo), desc=f"{method.name} scenes",
                            disable=None if progress else True, leave=False):
            for record in records:  # into this process's log (reproduce.log), as if fitted here
                logging.getLogger(record.name).handle(record)
        fresh = {s.name for s in todo}
    for scene in scenes:
        # fitted now by a worker: its time is in the caller's wall clock, not taken from a cache
        with method.uncounted() if scene.name in fresh else contextlib.nullcontext():
            method.fit_one_scene(scene, progress=progress)
