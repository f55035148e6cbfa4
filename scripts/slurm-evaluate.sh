#!/usr/bin/env bash
# Score one submission on a Slurm cluster: `skyeyes-bench evaluate --shard I/N` as a job array of N
# tasks (I = 0..N-1, $SLURM_ARRAY_TASK_ID), then `skyeyes-bench merge` of the N parts as a job that
# starts only when every task of the array succeeded (--dependency=afterok:<array job id>). The
# merged results equal one process's (docs/scale.md, "Slurm").
#
#   scripts/slurm-evaluate.sh [options] SUBMISSION N
#
# Options:
#   --out FILE          merged results (default: SUBMISSION.results.json beside the folder); the parts
#                       and the jobs' logs go to FILE's stem + .parts/ beside it
#   --data DIR          the dataset (default: what `evaluate` finds from submission.json)
#   --bench CMD         the command on the compute nodes (default: skyeyes-bench; e.g. /shared/venv/bin/skyeyes-bench,
#                       or "/shared/venv/bin/python -m skyeyes_bench.cli")
#   --sbatch "ARGS"     more sbatch options for the shard tasks, e.g. "--partition=gpu --gres=gpu:1 --time=2:00:00"
#   --merge-sbatch "ARGS"  more sbatch options for the merge job
#   --evaluate "ARGS"   more `evaluate` options for every shard, e.g. "--device cuda"
#   --force             let the merge replace an existing results file
#   --dry-run           print the commands instead of submitting them (the merge's JOBID is the array's)
#
# Every path must be one the compute nodes see (a shared file system): the submission, the dataset,
# the cache with the metric weights ($SKYEYES_CACHE, exported to the jobs as sbatch does by default).
set -euo pipefail

usage() { sed -n '2,/^set -euo/p' "$0" | sed '$d' | sed 's/^# \{0,1\}//'; }
die() { echo "slurm-evaluate.sh: error: $*" >&2; exit 2; }

out="" data="" bench="skyeyes-bench" extra="" merge_extra="" eval_extra="" force="" dry=0
pos=()
while [ $# -gt 0 ]; do
  case "$1" in
    --out) out=${2:?--out needs FILE}; shift 2 ;;
    --data) data=${2:?--data needs DIR}; shift 2 ;;
    --bench) bench=${2:?--bench needs CMD}; shift 2 ;;
    --sbatch) extra=${2?--sbatch needs ARGS}; shift 2 ;;
    --merge-sbatch) merge_extra=${2?--merge-sbatch needs ARGS}; shift 2 ;;
    --evaluate) eval_extra=${2?--evaluate needs ARGS}; shift 2 ;;
    --force) force=1; shift ;;
    --dry-run) dry=1; shift ;;
    -h|--help) usage; exit 0 ;;
    -*) die "unknown option $1 (see --help)" ;;
    *) pos+=("$1"); shift ;;
  esac
done
[ ${#pos[@]} -eq 2 ] || die "expected SUBMISSION N (see --help)"
sub=$(realpath -m -- "${pos[0]}")
n=${pos[1]}
[[ "$n" =~ ^[1-9][0-9]*$ ]] || die "N: expected a number of shards >= 1, got '$n'"
[ -f "$sub/submission.json" ] || die "$sub: not a submission folder (no submission.json)"
out=$(realpath -m -- "${out:-$sub.results.json}")
parts="${out%.json}.parts"
[ -n "$data" ] && data=$(realpath -m -- "$data")

# One argument as a shell word: as it is when plain, else in single quotes.
word() {
  if [[ "$1" =~ ^[A-Za-z0-9_./:=@%,+-]+$ ]]; then printf '%s' "$1"; else printf "'%s'" "${1//\'/\'\\\'\'}"; fi
}
line() { local a s=""; for a in "$@"; do s+="$(word "$a") "; done; echo "${s% }"; }

# The shard task's command line, run by the array task's shell: $SLURM_ARRAY_TASK_ID is expanded there.
read -r -a bench_words <<< "$bench"
task="$(line "${bench_words[@]}" evaluate "$sub") --shard \$SLURM_ARRAY_TASK_ID/$n --out $(word "$parts")/part-\$SLURM_ARRAY_TASK_ID.json --quiet --force"
[ -n "$data" ] && task+=" --data $(word "$data")"
[ -n "$eval_extra" ] && task+=" $eval_extra"
merge="$(line "${bench_words[@]}" merge)"
for ((i = 0; i < n; i++)); do merge+=" $(word "$parts/part-$i.json")"; done
merge+=" --out $(word "$out") --quiet"
[ -n "$force" ] && merge+=" --force"

read -r -a extra_args <<< "$extra"
read -r -a merge_args <<< "$merge_extra"
array_cmd=(sbatch --parsable --job-name=skyeyes-evaluate "--array=0-$((n - 1))" "--output=$parts/shard-%a.log"
           "${extra_args[@]}" "--wrap=$task")
merge_cmd=(sbatch --parsable --job-name=skyeyes-merge "--output=$parts/merge.log" "${merge_args[@]}")

if [ "$dry" = 1 ]; then
  line mkdir -p "$parts"
  line "${array_cmd[@]}"
  line "${merge_cmd[@]}" --dependency=afterok:JOBID "--wrap=$merge"
  exit 0
fi
command -v sbatch >/dev/null || die "sbatch not found: run this on a Slurm login node (or pass --dry-run)"
mkdir -p "$parts"
jobid=$("${array_cmd[@]}")
jobid=${jobid%%;*}  # --parsable prints "id" or "id;cluster"
merge_id=$("${merge_cmd[@]}" "--dependency=afterok:$jobid" "--wrap=$merge")
echo "submitted: shards as array job $jobid (0-$((n - 1))), merge as job ${merge_id%%;*} after it -> $out"
