"""Ray as an optional executor (`pip install 'skyeyes-bench[ray]'`): evaluation shards, scene fits
and the leaderboard intake's scoring as Ray tasks. The one module that imports Ray, and only when a
`--ray` command runs, so the default install never needs it (docs/scale.md).

```
with session(None):                          # a local Ray with this machine's cores (or ray.init(ADDRESS))
    got = evaluate_many([batch.Job(sub, out)])     # shards as tasks, merged by `shards.merge` into out
```

(`batch.evaluate_batch` is the entry point the commands use: in turn in the driver, or this.)

- **Shards.** A submission is split into N shards (`evaluate --shard I/N`: sequences k with
  k % N == I); each runs `evaluate.evaluate` as a task into a temporary folder on its worker and
  returns the part's two files as bytes; the driver writes them into a temporary folder of its own
  and merges them with `shards.merge`, which writes --out once (temporary names, then renames).
  So a worker must see the submission and the dataset (a shared path), never --out, and a failure
  leaves nothing in --out. `merge` makes the numbers those of one process whatever N is.
- **Faults.** A worker that dies mid-task (killed, out of memory, node lost) is retried by Ray up to
  `MAX_RETRIES` times and its shard computed again; an exception a task raises is not retried:
  a `UserError` (a submission that fails validation) comes back as a value and that submission is
  reported and skipped, the others still land; any other exception is a bug (traceback).
- **Environment.** Workers import the driver's code (`_runtime_env`: a source checkout's folder on
  their PYTHONPATH) and each task runs with the driver's `FORWARDED` variables (cache, protocols).
"""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Iterator

from .errors import UserError, ValidationError, one_line

#: The command that installs Ray with this package (the one line `--ray` prints without it).
INSTALL = "pip install 'skyeyes-bench[ray]'"
#: Retries of a task whose worker died (Ray's `max_retries`; exceptions are never retried).
MAX_RETRIES = 3
#: Test hook (docs/scale.md, "Faults"): the first shard task that creates this file (it must not
#: exist) kills its own worker process after computing its part and before returning it.
CRASH_ENV = "SKYEYES_RAY_CRASH_ONCE"
#: The driver's variables every task runs with (unset in the driver: unset in the task).
FORWARDED = ("SKYEYES_CACHE", "SKYEYES_PROTOCOLS", CRASH_ENV)


def require_ray():
    """The `ray` module, or a one-line UserError (exit 2) that says how to install it."""
    try:
        import ray
    except ImportError:
        raise UserError(f"--ray needs Ray, which is not installed here; install it with: {INSTALL}") from None
    return ray


def _runtime_env() -> dict:
    """Workers import this code: a source checkout's folder goes first on their PYTHONPATH (an
    installed package needs nothing; a remote cluster needs the checkout on a shared path)."""
    from . import paths

    repo = paths.repo_root()
    if repo is None:
        return {}
    entries = [str(repo), *(p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p)]
    return {"env_vars": {"PYTHONPATH": os.pathsep.join(dict.fromkeys(entries))}}


@contextlib.contextmanager
def session(address: str | None = None, *, num_cpus: int | None = None) -> Iterator[Any]:
    """Ray for the block: `ray.init(address=address)`, else a local Ray with `num_cpus` (default:
    this machine's cores); shut down afterwards. A Ray this process already initialised is used as
    it is and left running. Yields the `ray` module."""
    ray = require_ray()
    if ray.is_initialized():
        yield ray
        return
    kw: dict[str, Any] = {"include_dashboard": False, "logging_level": logging.WARNING,
                          "runtime_env": _runtime_env()}
    if address:
        kw["address"] = address
    else:
        kw["num_cpus"] = num_cpus or os.cpu_count() or 1
    try:
        ray.init(**kw)
    except (ConnectionError, RuntimeError, ValueError) as e:
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise UserError(f"--ray {address or ''}: no Ray cluster could be reached or started ({first}); expected the "
                        "address of a running cluster (HOST:PORT, ray://HOST:PORT, auto) or none for a local Ray"
                        ) from None
    try:
        yield ray
    finally:
        ray.shutdown()


def forwarded_env() -> dict[str, str | None]:
    """The driver's `FORWARDED` variables (None: unset)."""
    return {k: os.environ.get(k) for k in FORWARDED}


@contextlib.contextmanager
def _environment(env: dict[str, str | None]) -> Iterator[None]:
    """Within the block the process has `env` (None: unset); restored after (a Ray worker is
    reused by the tasks that follow)."""
    def put(values):
        for k, v in values.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v

    old = {k: os.environ.get(k) for k in env}
    put(env)
    try:
        yield
    finally:
        put(old)


def _crash_once() -> None:
    """The `CRASH_ENV` test hook: the worker exits at once, as if killed, the first time only."""
    marker = os.environ.get(CRASH_ENV)
    if not marker:
        return
    try:
        os.close(os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return
    os._exit(1)


def slots(gpu: bool = False) -> int:
    """Tasks the cluster runs at once: its GPUs for GPU tasks, else its CPUs (one each)."""
    ray = require_ray()
    return max(1, int(ray.cluster_resources().get("GPU" if gpu else "CPU", 1)))


def plan_device(device: str | None) -> tuple[str, float]:
    """(the device each shard task scores on, the GPUs it asks Ray for) for `--device`: cpu (the
    reference), auto (a GPU per task where the cluster has GPUs, else the CPU), or cuda."""
    ray = require_ray()
    d = device or "cpu"
    gpus = ray.cluster_resources().get("GPU", 0)
    if d == "cpu":
        return "cpu", 0
    if d == "auto":
        return ("cuda", 1) if gpus else ("cpu", 0)
    if d.startswith("cuda"):
        if not gpus:
            raise UserError(f"--device {d}: the Ray cluster has no GPU; expected cpu or auto there")
        return "cuda", 1  # Ray gives each task its own GPU (CUDA_VISIBLE_DEVICES): cuda:N means nothing here
    raise UserError(f"--device {d}: with --ray expected cpu, auto or cuda")


# --------------------------------------------------------------------------- generic tasks


def _call(fn: Callable, args: tuple, env: dict) -> Any:
    """Task body: `fn(*args)` with the driver's environment."""
    with _environment(env):
        return fn(*args)


def map_unordered(fn: Callable, calls: list[tuple], *, num_cpus: float = 1, num_gpus: float = 0) -> Iterator[Any]:
    """`fn(*args)` for each `args` of `calls` as Ray tasks (retried where a worker dies); yields
    the results as they complete. An exception a task raises is raised here."""
    ray = require_ray()
    task = ray.remote(_call).options(num_cpus=num_cpus, num_gpus=num_gpus, max_retries=MAX_RETRIES,
                                     retry_exceptions=False)
    env = forwarded_env()
    pending = [task.remote(fn, args, env) for args in calls]
    while pending:
        done, pending = ray.wait(pending, num_returns=1)
        yield ray.get(done[0])


# --------------------------------------------------------------------------- evaluation


def part_name(shard: tuple[int, int]) -> str:
    """A shard's part file name (the same on the worker and the driver: a part names its sidecar)."""
    return f"shard-{shard[0]}-of-{shard[1]}.json"


def _score_shard(sub: str, data: str, shard: tuple[int, int], protocol: str, device: str,
                 env: dict, allow_missing: bool = True) -> dict:
    """Task: `evaluate --shard` into a temporary folder; the part's JSON and sidecar as bytes, or
    {"error", "exit_code"} for a user error."""
    from .evaluate import evaluate
    from .results import features_path

    with _environment(env), tempfile.TemporaryDirectory(prefix="skyeyes-shard-") as tmp:
        out = Path(tmp) / part_name(shard)
        t0 = time.perf_counter()
        try:
            evaluate(sub, data=data, out=out, shard=shard, progress=False, protocol=protocol, device=device,
                     allow_missing=allow_missing)  # checked on the worker: its weights are the ones that count
        except UserError as e:
            return {"error": one_line(e), "exit_code": e.exit_code}
        got = {"json": out.read_bytes(), "features": features_path(out).read_bytes(),
               "seconds": time.perf_counter() - t0}
        _crash_once()
        return got


def _prepare(job, force: bool) -> tuple[str, str, str, int]:
    """The driver's checks before any task: the output, the submission's manifest, protocol and
    dataset, and its files (without decoding them; each shard decodes its own frames). Returns
    (submission, dataset root, protocol ref, test sequences), paths absolute for the workers."""
    from .evaluate import check_extractors, check_out, open_inputs
    from .submission import validate_submission

    sub = Path(job.sub)
    check_out(job.out, force, [sub])
    manifest, protocol, ds = open_inputs(sub, job.data, job.protocol)
    check_out(job.out, force, [sub, ds.root])
    check_extractors(protocol)
    problems = validate_submission(sub, ds, protocol, manifest, decode=False)
    if problems:
        raise ValidationError(f"submission {sub}", problems)
    return str(sub.resolve()), str(Path(ds.root).resolve()), protocol.ref, len(ds.sequences("test"))


def _merge(job, got: dict, parts: dict[int, dict], n: int, force: bool) -> None:
    """Write the parts into a temporary folder and merge them into `job.out`; `got` (the job's
    outcome) gets the results or the error, and the seconds of each shard and of the merge."""
    from .evaluate import merge
    from .results import features_path

    with tempfile.TemporaryDirectory(prefix="skyeyes-ray-parts-") as tmp:
        files = []
        for k in range(n):
            p = Path(tmp) / part_name((k, n))
            p.write_bytes(parts[k]["json"])
            features_path(p).write_bytes(parts[k]["features"])
            files.append(p)
        t0 = time.perf_counter()
        try:
            got["results"] = merge(files, out=job.out, force=force, progress=False)
        except UserError as e:
            got.update(error=one_line(e), exit_code=e.exit_code)
        got["merge_s"] = time.perf_counter() - t0
    got["shard_s"] = [parts[k]["seconds"] for k in range(n)]


def evaluate_many(jobs: list, *, shards: int | None = None, device: str | None = "cpu", force: bool = False,
                  progress: bool = True, allow_missing: bool = True) -> list[dict]:
    """Score every job's submission (`batch.Job`: sub, out, data, protocol) as shard tasks in the
    running Ray (`session`); merge each into its `out` as soon as its shards are in. shards: per
    submission (default: one per task the cluster runs at once, at most one per test sequence).
    Returns per job {"results", "error", "exit_code", "shard_s", "merge_s"} (`batch.Outcome`)."""
    from .results import progress_bar

    ray = require_ray()
    dev, gpus = plan_device(device)
    task = ray.remote(_score_shard).options(num_cpus=1, num_gpus=gpus, max_retries=MAX_RETRIES,
                                            retry_exceptions=False)
    env = forwarded_env()
    outcomes = [{"results": None, "error": None, "exit_code": 0, "shard_s": [], "merge_s": 0.0} for _ in jobs]
    pending: dict[Any, tuple[int, int]] = {}  # task -> (job, shard)
    counts: dict[int, int] = {}
    for i, job in enumerate(jobs):
        try:
            sub, data, ref, n_seq = _prepare(job, force)
        except UserError as e:
            outcomes[i].update(error=one_line(e), exit_code=e.exit_code)
            continue
        counts[i] = n = max(1, min(n_seq, shards or slots(gpus > 0)))
        for k in range(n):
            pending[task.remote(sub, data, (k, n), ref, dev, env, allow_missing)] = (i, k)
    parts: dict[int, dict[int, dict]] = {}
    with progress_bar(progress, total=len(pending), desc="shards", unit="shard") as bar:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            i, k = pending.pop(done[0])
            bar.update(1)
            got = _result(ray, done[0], k, counts[i])
            if outcomes[i]["error"] is not None:
                continue
            if "error" in got:
                outcomes[i].update(error=got["error"], exit_code=got["exit_code"])
                continue
            parts.setdefault(i, {})[k] = got
            if len(parts[i]) == counts[i]:
                _merge(jobs[i], outcomes[i], parts.pop(i), counts[i], force)
    return outcomes


def _result(ray, ref, k: int, n: int) -> dict:
    """A shard task's result; a task that could not finish (its worker died more than
    `MAX_RETRIES` times, its node was lost) as an error of that submission (exit 1)."""
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError:
        raise  # an exception in evaluate that is no user error: a bug, with its traceback
    except ray.exceptions.RayError as e:
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        return {"error": f"shard {k}/{n} did not finish on Ray after {MAX_RETRIES} retries: {first}", "exit_code": 1}
