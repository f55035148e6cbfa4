"""scripts/slurm-evaluate.sh (issue 38): the sbatch commands it submits (a job array of
`evaluate --shard I/N`, I = 0..N-1, and `merge` after it with --dependency=afterok), checked
word for word in a dry run; and run through a stand-in `sbatch` that executes each job's command
line as Slurm would, the merged results equal one process's."""

import json
import os
import subprocess
import sys

from conftest import ROOT, run_cli
from builders.evaluation import blurred_submission, make_dataset, protocol_env, scores

SCRIPT = ROOT / "scripts" / "slurm-evaluate.sh"

#: A stand-in for sbatch: runs `--wrap` in bash, once per index of `--array=0-K` with
#: SLURM_ARRAY_TASK_ID set, and prints a job id as `sbatch --parsable` does; logs its arguments.
FAKE_SBATCH = r"""#!/usr/bin/env bash
set -euo pipefail
printf '%s\n' "$*" >> "$SBATCH_LOG"
array="" wrap=""
for a in "$@"; do
  case "$a" in --array=*) array=${a#--array=} ;; --wrap=*) wrap=${a#--wrap=} ;; esac
done
if [ -n "$array" ]; then
  for ((i = ${array%-*}; i <= ${array#*-}; i++)); do SLURM_ARRAY_TASK_ID=$i bash -c "$wrap"; done
else
  bash -c "$wrap"
fi
echo "$((RANDOM + 1000))"
"""


def dry_run(*args: str) -> list[str]:
    got = subprocess.run(["bash", str(SCRIPT), "--dry-run", *args], capture_output=True, text=True, check=True)
    return got.stdout.splitlines()


def test_dry_run_prints_the_array_and_the_dependent_merge(tmp_path):
    sub = tmp_path / "sub"
    sub.mkdir()
    (sub / "submission.json").write_text("{}")
    p = f"{tmp_path}/r.parts"
    assert dry_run(str(sub), "3", "--out", str(tmp_path / "r.json"), "--data", "/shared/data",
                   "--sbatch", "--partition=gpu --gres=gpu:1", "--evaluate", "--device cuda") == [
        f"mkdir -p {p}",
        f"sbatch --parsable --job-name=skyeyes-evaluate --array=0-2 --output={p}/shard-%a.log --partition=gpu "
        f"--gres=gpu:1 '--wrap=skyeyes-bench evaluate {sub} --shard $SLURM_ARRAY_TASK_ID/3 --out "
        f"{p}/part-$SLURM_ARRAY_TASK_ID.json --quiet --force --data /shared/data --device cuda'",
        f"sbatch --parsable --job-name=skyeyes-merge --output={p}/merge.log --dependency=afterok:JOBID "
        f"'--wrap=skyeyes-bench merge {p}/part-0.json {p}/part-1.json {p}/part-2.json --out {tmp_path}/r.json "
        f"--quiet'"]
    # the default --out is beside the folder; bad input is one line, exit 2
    assert dry_run(str(sub), "1")[2].endswith(f"--wrap=skyeyes-bench merge {sub}.results.parts/part-0.json --out "
                                              f"{sub}.results.json --quiet'")
    for bad, why in ((["0"], "N: expected a number of shards >= 1"), ([], "expected SUBMISSION N"),
                     (["2", "--shards"], "unknown option --shards")):
        got = subprocess.run(["bash", str(SCRIPT), "--dry-run", str(sub), *bad], capture_output=True, text=True)
        assert got.returncode == 2 and why in got.stderr and got.stderr.count("\n") == 1, got.stderr


def test_the_jobs_merge_to_the_numbers_of_one_process(tmp_path, monkeypatch):
    with protocol_env(tmp_path) as mp:
        from skyeyes_bench.data.layout import open_dataset

        ds = open_dataset(make_dataset(tmp_path / "ds", scenes=3))
        sub = blurred_submission(ds, tmp_path / "sub")
        run_cli("evaluate", "--allow-missing", str(sub), "--data", str(ds.root), "--out", str(tmp_path / "one.json"), "--quiet")
        mp.setenv("SKYEYES_CACHE", str(tmp_path / "other-cache"))  # the jobs compute their own features
        bin_dir = tmp_path / "bin"
        bin_dir.mkdir()
        (bin_dir / "sbatch").write_text(FAKE_SBATCH)
        (bin_dir / "sbatch").chmod(0o755)
        env = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}", "SBATCH_LOG": str(tmp_path / "sbatch.log"),
               "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
        got = subprocess.run(["bash", str(SCRIPT), str(sub), "2", "--data", str(ds.root), "--out",
                              str(tmp_path / "slurm.json"), "--bench", f"{sys.executable} -m skyeyes_bench.cli",
                              "--evaluate", "--allow-missing"],  # LPIPS: no weights in the test's cache
                             capture_output=True, text=True, env=env, timeout=300)
        assert got.returncode == 0, got.stderr
        assert "submitted: shards as array job" in got.stdout
    log = (tmp_path / "sbatch.log").read_text().splitlines()
    assert "--array=0-1" in log[0] and "--dependency=afterok:" in log[1]
    one, slurm = (scores(json.loads((tmp_path / f"{n}.json").read_text())) for n in ("one", "slurm"))
    assert slurm == one
    assert slurm["metrics"]["fid"]["status"] == "ok"
