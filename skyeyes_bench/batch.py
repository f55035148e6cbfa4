"""Several submissions scored by one command (`evaluate SUB...`, `leaderboard evaluate INBOX/`):
in turn in this process, or, with `--ray`, as shards on Ray (`ray_exec`, imported only then).
Either way a submission that cannot be scored is an `Outcome` with its one-line error and the
others are still scored; each results file is written whole or not at all.

```
outcomes = evaluate_batch([Job(sub, out)], ray=None)    # in turn, here
outcomes = evaluate_batch(jobs, ray="")                  # a local Ray; ray="HOST:PORT": a cluster
```
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from .errors import UserError, one_line

#: What `--ray ADDRESS` accepts: Ray's own words, HOST:PORT, or a ray:// client address.
_ADDRESS = re.compile(r"auto|local|ray://\S+|[^\s/:]+:\d+")

#: The help line of every `--ray` flag (evaluate, reproduce, leaderboard evaluate).
RAY_HELP = ("run on Ray (pip install 'skyeyes-bench[ray]'): the cluster at ADDRESS (HOST:PORT, ray://HOST:PORT, "
            "auto), or without one a local Ray with this machine's cores; inputs must lie on a path every worker "
            "sees (docs/scale.md)")
#: ... and where a command also takes folders (argparse would give `--ray FOLDER` the folder).
RAY_ORDER = ". Put it after the folders, or write --ray=ADDRESS"


@dataclass
class Job:
    """One submission to score: its folder, the results file, and `evaluate`'s --data and --protocol."""

    sub: Path
    out: Path
    data: str | None = None
    protocol: str | None = None


@dataclass
class Outcome:
    """What became of a `Job`: its results, or the one line that says why not (and its exit code);
    on Ray also the seconds each shard task took on its worker and the driver's merge."""

    job: Job
    results: dict | None = None
    error: str | None = None
    exit_code: int = 0
    shard_s: list[float] = field(default_factory=list)
    merge_s: float = 0.0


def ray_address(value: str | None, folders: list[str]) -> str | None:
    """`--ray [ADDRESS]` as argparse left it: None (not given), "" (a local Ray) or an address.
    argparse gives `--ray SUB` the folder SUB as ADDRESS: a value that is no address but a folder
    here goes back to the front of `folders` (in place)."""
    if value is None or value == "" or _ADDRESS.fullmatch(value):
        return value
    if Path(value).is_dir():
        folders.insert(0, value)
        return ""
    raise UserError(f"--ray {value}: expected a Ray address (HOST:PORT, ray://HOST:PORT, auto or local) or no value "
                    "for a local Ray")


def evaluate_batch(jobs: list[Job], *, ray: str | None = None, shards: int | None = None, device: str | None = "cpu",
                   force: bool = False, progress: bool = True, allow_missing: bool = True) -> list[Outcome]:
    """Score each job: `ray` None: in turn with `evaluate.evaluate`; else as shard tasks on the Ray
    at that address ("": a local one; `ray_exec.evaluate_many`). shards: per submission on Ray.
    allow_missing: as `evaluate.evaluate`'s (False: a job whose protocol asks for a metric that
    cannot be computed fails with that one line)."""
    if shards is not None and shards < 1:
        raise UserError(f"--shards {shards}: expected a number of shards >= 1")
    if ray is None:
        return [_here(job, device, force, progress, allow_missing) for job in jobs]
    from . import ray_exec

    with ray_exec.session(ray or None):
        got = ray_exec.evaluate_many(jobs, shards=shards, device=device, force=force, progress=progress,
                                     allow_missing=allow_missing)
    return [Outcome(job, **g) for job, g in zip(jobs, got)]


def exit_code(outcomes: list[Outcome]) -> int:
    """0 when every job was scored; else `combined_exit` of the failed ones' codes."""
    return combined_exit([o.exit_code for o in outcomes if o.error is not None])


def combined_exit(codes: list[int]) -> int:
    """One exit code for several failures: 0 for none, 1 if any was internal, else the largest (2: invalid input)."""
    return 0 if not codes else 1 if 1 in codes else max(codes)


def _here(job: Job, device, force: bool, progress: bool, allow_missing: bool = True) -> Outcome:
    from .evaluate import evaluate

    try:
        return Outcome(job, results=evaluate(job.sub, data=job.data, out=job.out, force=force, progress=progress,
                                             protocol=job.protocol, device=device, allow_missing=allow_missing))
    except UserError as e:
        return Outcome(job, error=one_line(e), exit_code=e.exit_code)
