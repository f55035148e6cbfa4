"""Mutation testing: how many small bugs planted in a module the default test tier kills.

Runs mutmut (3.x, the `dev` extra) on a throwaway copy of the repository at HEAD (`git archive`,
so neither the working tree nor other people's uncommitted changes are touched), with the
default tier (`pytest -m 'not slow'`, pyproject's addopts) or the tests you name, and prints the
kill rate per module:

    nice -n 19 .venv/bin/python bench/mutation.py                          # the four modules below
    nice -n 19 .venv/bin/python bench/mutation.py --module skyeyes_bench/stats.py \\
        --tests tests/skyeyes_bench/test_stats.py --time-limit 1800

Default modules (issue 21): skyeyes_bench/metrics, skyeyes_bench/stats.py, skyeyes_bench/scoring
and the rasterizer (reference/common/gaussians/{raster,project}.py). CPU-heavy: mutmut first runs
the selected tests once to learn which tests reach which function, then, per mutant, only those.
The whole campaign with the default tier is hours on 2 cores; give --tests and --time-limit, or
measure the rate on a random sample of mutants per module (--sample N; exact binomial 95%
interval; with N = 150 and a rate near 85% the interval is about +-6 points):

    .venv/bin/python bench/mutation.py --sample 150 --max-children 2

mutmut's operators (mutmut/mutation/mutators.py): numbers (n -> n + 1), strings ("x" -> "XXxXX"),
keywords and names (True/False, None, and/or, in/not in, is/is not, break/continue), binary,
comparison and augmented operators swapped (+ -, * /, < <=, == !=, ...), unary operators removed,
call arguments removed or set to None, dict keyword arguments renamed, lambdas' bodies replaced,
assignments replaced by None, if-expressions' branches swapped, string-method pairs swapped
(lower/upper, lstrip/rstrip, ...).

The campaigns run so far and their kill rates are in docs/log/runs-2026.md.

Run it on an idle machine: beside other jobs, tests that run far past their unloaded time are
marked "timeout" (starved, not killed).

Kill rate = (killed + timeout) / (mutants checked). "no tests" (no selected test reaches the
function) counts as survived; mutants not checked before the time limit are left out and
counted in the output. Equivalent mutants are not detected automatically: read the survivors
(`--show N` prints their diffs) and judge.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MODULES = ["skyeyes_bench/metrics", "skyeyes_bench/stats.py", "skyeyes_bench/scoring",
                   "reference/common/gaussians/raster.py", "reference/common/gaussians/project.py"]
#: What the tests read besides the packages (mutmut copies tests/ and pyproject.toml itself).
ALSO_COPY = ["protocols", "leaderboard", "bench", "scripts", "docs", "README.md"]
DETECTED = {"killed", "timeout", "caught by type check", "segfault"}
NOT_RUN = {"not checked", "skipped", "check was interrupted by user"}


def _status_table():
    from mutmut.stats import status_by_exit_code

    return status_by_exit_code


def prepare(workdir: Path, modules: list[str], tests: list[str], pytest_args: list[str], isolation: str) -> None:
    """A copy of HEAD in `workdir` with a [tool.mutmut] section naming what to mutate."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", "HEAD"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(workdir)], input=archive, check=True)
    # Whole packages are copied into mutants/ (so `skyeyes_bench` and `reference` import from
    # there, never from the editable install); only `modules` are mutated.
    only = [m.rstrip("/") + ("/*" if (workdir / m).is_dir() else "") for m in modules]
    for m in modules:
        if not (workdir / m).exists():
            raise SystemExit(f"--module {m}: no such file or folder at HEAD")
    conf = {
        "source_paths": ["skyeyes_bench", "reference"],
        "only_mutate": only,
        "also_copy": [p for p in ALSO_COPY if (workdir / p).exists()],
        "pytest_add_cli_args": ["-p", "no:cacheprovider", "-q", "-x", *pytest_args],
        "pytest_add_cli_args_test_selection": tests,
        "use_git_change_detection": False,
        # Numeric tests legitimately take seconds; a mutant looping forever is cut at 15x + 10 s.
        "timeout_constant": 10.0,
        # "forkserver" (the default): forking a process whose earlier tests ran torch's thread
        # pools can hang the child, idle, until mutmut's timeout counts it a kill. Seen with
        # fork: evaluate.py's campaign idled on mutants its tests pass in 11 s. "fork" is faster
        # when no selected test runs torch.
        "process_isolation": isolation,
    }
    lines = ["", "[tool.mutmut]"] + [f"{k} = {json.dumps(v)}" for k, v in conf.items()]
    with open(workdir / "pyproject.toml", "a") as f:
        f.write("\n".join(lines) + "\n")


#: A mutant name no mutant has: `mutmut run` with it generates the mutants and maps tests to
#: functions (the stats it keeps for the next run), then stops before testing any mutant.
NO_MUTANT = "skyeyes-bench-generate-only"


def run_mutmut(workdir: Path, max_children: int, time_limit: float | None,
               names: list[str] | None = None) -> tuple[int | None, float]:
    """`mutmut run [names]` in workdir (its own process group), stopped after time_limit seconds."""
    # SKYEYES_MUTATION: tests/conftest.py reloads extractor networks per test (complete mapping)
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1", SKYEYES_MUTATION="1")
    env.pop("SKYEYES_CACHE", None)
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "mutmut", "run", "--max-children", str(max_children),
                             *(names or [])], cwd=workdir, env=env, start_new_session=True)
    try:
        rc = proc.wait(timeout=time_limit)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        rc = None
    return rc, time.monotonic() - t0


def mutant_codes(workdir: Path, modules: list[str]) -> dict[str, dict[str, int | None]]:
    """{module: {mutant name: mutmut exit code (None: not checked)}} from mutmut's .meta files; a
    module is a file, or a folder's files together."""
    out: dict[str, dict[str, int | None]] = {m: {} for m in modules}
    for meta in sorted((workdir / "mutants").rglob("*.py.meta")):
        rel = meta.relative_to(workdir / "mutants").as_posix()[:-len(".meta")]
        owner = next((m for m in modules if rel == m or rel.startswith(m.rstrip("/") + "/")), None)
        if owner is not None:
            out[owner].update(json.loads(meta.read_text()).get("exit_code_by_key", {}))
    return out


def sample_mutants(names_by_module: dict[str, list[str]], n: int, seed: int) -> dict[str, list[str]]:
    """Up to n mutant names per module, drawn without replacement (uniformly, from `seed`; the
    same names for the same mutants and seed, whatever order they were listed in)."""
    import random

    return {m: sorted(random.Random(f"{seed}:{m}").sample(sorted(names), min(n, len(names))))
            for m, names in names_by_module.items()}


def collect(workdir: Path, modules: list[str], only: dict[str, list[str]] | None = None) -> dict[str, Counter]:
    """Status counts per module; with `only`, of those mutants alone (a sample)."""
    table = _status_table()
    out = {}
    for m, codes in mutant_codes(workdir, modules).items():
        keep = set(only[m]) if only is not None else codes.keys()
        out[m] = Counter(table[c] for k, c in codes.items() if k in keep)
    return out


def rate_interval(killed: int, checked: int, level: float = 0.95) -> tuple[float, float]:
    """Clopper-Pearson (exact binomial) interval of a kill rate measured on a random sample."""
    from scipy.stats import binomtest

    ci = binomtest(killed, checked).proportion_ci(confidence_level=level, method="exact")
    return float(ci.low), float(ci.high)


def survivors(workdir: Path, modules: list[str], only: dict[str, list[str]] | None = None) -> list[str]:
    table = _status_table()
    return [k for m, codes in mutant_codes(workdir, modules).items() for k, c in codes.items()
            if table[c] in ("survived", "no tests") and (only is None or k in only[m])]


def report(counts: dict[str, Counter], population: dict[str, int] | None = None) -> list[dict]:
    """Print and return the figures per module. With `population` (the module's mutant count, for
    a sampled campaign) the counts are the sample's and each rate gets its 95% interval."""
    sampled = population is not None
    if sampled:
        print("a uniform random sample of each module's mutants (its size: 'mutants'; of how many: 'of')")
    rows = []
    print(f"{'module':<42} {'mutants':>7} {'checked':>7} {'killed':>6} {'t/out':>5} {'surv.':>5} {'no test':>7} "
          f"{'kill rate':>9}" + ("  95% interval (exact binomial)" if sampled else ""))
    for m, c in counts.items():
        total = sum(c.values())
        checked = total - sum(c[s] for s in NOT_RUN)
        killed = sum(c[s] for s in DETECTED)
        rate = killed / checked if checked else float("nan")
        row = {"module": m, "mutants": total, "checked": checked, "killed": killed, "timeout": c["timeout"],
               "survived": c["survived"], "no_tests": c["no tests"], "suspicious": c["suspicious"],
               "kill_rate": rate}
        if sampled:
            row["population"] = population[m]
        line = f"{m:<42} {total:>7}{f' of {population[m]}' if sampled else ''} {checked:>7} {killed:>6} {c['timeout']:>5} {c['survived']:>5} {c['no tests']:>7} "
        if checked:
            line += f"{rate:>8.1%}"
            if sampled:
                row["interval_95"] = rate_interval(killed, checked)
                line += "  [{:.1%}, {:.1%}]".format(*row["interval_95"])
        rows.append(row)
        print(line if checked else f"{m:<42} {total:>7} {checked:>7}" + " " * 6 + "-")
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--module", action="append", help="file or folder to mutate (repeatable; default: the four "
                    "of issue 21)")
    ap.add_argument("--tests", action="append", default=[], help="pytest path / node id selecting the tests "
                    "(repeatable; default: all of tests/, default tier)")
    ap.add_argument("--pytest-arg", action="append", default=[], help="extra pytest argument (repeatable)")
    ap.add_argument("--time-limit", type=float, default=None, help="stop mutmut after this many seconds")
    ap.add_argument("--max-children", type=int, default=1, help="parallel mutant runs (default 1: shared cores)")
    ap.add_argument("--isolation", choices=["fork", "forkserver"], default=None,
                    help="mutmut process_isolation (default forkserver; fork is faster, and safe only when no "
                         "selected test runs torch)")
    ap.add_argument("--workdir", type=Path, help="keep the copy here (default: a temporary folder, removed)")
    ap.add_argument("--json", type=Path, help="also write the per-module figures here")
    ap.add_argument("--show", type=int, default=0, help="print the diffs of up to N surviving mutants")
    ap.add_argument("--sample", type=int, default=0, metavar="N",
                    help="test a uniform random sample of N mutants per module (0: all) and give each kill rate "
                         "its exact binomial 95%% interval; the rest stay 'not checked'")
    ap.add_argument("--seed", type=int, default=0, help="seed of --sample (default 0)")
    args = ap.parse_args()
    try:
        import mutmut  # noqa: F401
    except ImportError:
        print("mutmut is missing: .venv/bin/python -m pip install -e '.[dev]'", file=sys.stderr)
        return 2
    modules = args.module or DEFAULT_MODULES
    keep = args.workdir is not None
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="skyeyes-mutation-"))
    workdir.mkdir(parents=True, exist_ok=True)
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()  # what `prepare` archives
    try:
        if not (workdir / "mutants").exists():
            isolation = args.isolation or "forkserver"
            prepare(workdir, modules, args.tests, args.pytest_arg, isolation)
        only = None
        if args.sample:
            # 1. generate the mutants and map tests to functions (kept for 2.); 2. test the sample.
            pre_rc, pre_s = run_mutmut(workdir, args.max_children, args.time_limit, [NO_MUTANT])
            by_module = {m: list(codes) for m, codes in mutant_codes(workdir, modules).items()}
            if pre_rc is None or not any(by_module.values()):
                raise SystemExit(f"mutmut did not generate mutants (rc {pre_rc}, {pre_s:.0f} s); see its output above")
            only = sample_mutants(by_module, args.sample, args.seed)
            left = None if args.time_limit is None else max(1.0, args.time_limit - pre_s)
            rc, seconds = run_mutmut(workdir, args.max_children, left, [k for ks in only.values() for k in ks])
            seconds += pre_s
        else:
            rc, seconds = run_mutmut(workdir, args.max_children, args.time_limit)
        stopped = " (stopped at the time limit: unchecked mutants left out)" if rc is None else ""
        drawn = f"; a sample of {args.sample} mutants per module (seed {args.seed})" if args.sample else ""
        print(f"\nmutmut on {head}, tests: {' '.join(args.tests) or 'tests/ (default tier)'}; "
              f"{seconds:.0f} s{stopped}{drawn}")
        rows = report(collect(workdir, modules, only),
                      None if only is None else {m: len(ks) for m, ks in by_module.items()})
        if args.show:
            names = survivors(workdir, modules, only)
            print(f"\n{len(names)} surviving mutants" + (f"; the first {args.show}:" if names else ""))
            for name in names[:args.show]:
                r = subprocess.run([sys.executable, "-m", "mutmut", "show", name], cwd=workdir, capture_output=True,
                                   text=True)
                print(r.stdout)
        if args.json:
            args.json.write_text(json.dumps({"commit": head, "tests": args.tests, "seconds": round(seconds),
                                             "stopped_at_limit": rc is None, "sample": args.sample,
                                             "seed": args.seed, "modules": rows}, indent=1) + "\n")
    finally:
        if not keep:
            shutil.rmtree(workdir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
