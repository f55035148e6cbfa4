#!/usr/bin/env bash
# The one prepared check of the reference side on a bare GPU machine (issue 34; docs/gpu.md).
#
# The machine has PyTorch with CUDA and no network. What else the project needs comes as wheels
# in .whl/ beside the checkout (`bash scripts/gpu-wheels.sh`, run where there is network). From
# the repository root:
#
#   bash scripts/gpu-check.sh          # all: data, every method's smoke on CUDA, skyeyes small
#   bash scripts/gpu-check.sh tests    # the test suite's `gpu` tests (not slow), on their own
#   bash scripts/gpu-check.sh more     # the submission parts a first run could not hand back
#
# `all`, in at most 10 minutes on one H100:
#   1. SynthTown smoke and small generated with every core;
#   2. `reproduce --preset smoke --device cuda` of every method, 5 at a time, each with its own
#      cache (the README's first command is the skyeyes one);
#   3. `reproduce --method skyeyes --preset small --device cuda`, timed end to end (data not
#      counted), with each stage's seconds and the peak GPU memory (all processes, nvidia-smi);
#   4. the skyeyes small submission packed (a tar in 15 MB parts) for scoring on a machine that
#      has the metric weights: `cat skyeyes-small.tar.part-* | tar x`, then `skyeyes-bench evaluate`.
# A dry run of the plumbing on a CPU machine: DEVICE=cpu SMALL=smoke METHODS="mean-frame sugar skyeyes".
# Everything it prints goes to $OUT/gpu-check.log; $OUT (default ./gpu-check-out) receives at most
# 8 files and 64 MB, the limits of what a lent machine hands back; the rest stays in .gpu-check/.
set -uo pipefail
cd "$(dirname "$0")/.."
mode=${1:-all}
DEVICE=${DEVICE:-cuda}  # cpu: a dry run of this script's plumbing where there is no GPU
SMALL=${SMALL:-small}   # the preset timed end to end (smoke for a dry run)
OUT=${OUT:-$PWD/gpu-check-out}
W=$PWD/.gpu-check  # work folder (git-ignored through .git/info/exclude where the checkout is a clone)
mkdir -p "$OUT" "$W"
exec > >(tee -a "$OUT/gpu-check.log") 2>&1
export PYTHONUNBUFFERED=1 TQDM_DISABLE=1

# 0. the wheels this machine lacks, installed aside (never into the image's own environment)
site=/tmp/skyeyes-site
if ls .whl/*.whl >/dev/null 2>&1 && [ ! -d "$site" ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$site" .whl/*.whl \
    || { echo "gpu-check: installing .whl/*.whl failed"; exit 1; }
fi
export PYTHONPATH=$site:$PWD${PYTHONPATH:+:$PYTHONPATH}
export SKYEYES_CACHE=$W/cache
sb=(python3 -m skyeyes_bench.cli)  # an array, so `timeout` can run it (it cannot run a function)
stages=$OUT/stages.tsv
stage() {  # stage NAME SECONDS_LIMIT CMD...: run, time, record "name seconds rc"
  local name=$1 limit=$2; shift 2
  local t0=$SECONDS
  timeout "$limit" "$@"; local rc=$?
  printf '%s\t%d\t%d\n' "$name" $((SECONDS - t0)) "$rc" | tee -a "$stages"
  return $rc
}

if [ "$mode" = more ]; then  # the parts the first run left behind (same warm machine)
  ls "$W"/skyeyes-small.tar.part-* 2>/dev/null | tail -n +4 | head -n 7 | xargs -r cp -t "$OUT"
  ls -la "$OUT"
  exit 0
fi

echo "== gpu-check $mode at $(git rev-parse --short HEAD 2>/dev/null || echo '?') on $(hostname), $(date -u +%FT%TZ)"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || echo "no nvidia-smi"
python3 -c "import os, torch, diffusers; print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'no GPU', '| diffusers', diffusers.__version__, '| cores', os.cpu_count())"

if [ "$mode" = tests ]; then
  stage gpu-tests 540 python3 -m pytest -q -p no:cacheprovider -m "gpu and not slow" tests
  exit $?
fi
[ "$mode" = all ] || { echo "usage: bash scripts/gpu-check.sh [all|tests|more]"; exit 2; }

printf 'stage\tseconds\trc\n' > "$stages"
# peak GPU memory over all processes (the prior's lane workers hold their own)
nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -lms 500 > "$W/gpumem.log" 2>/dev/null &
sampler=$!
trap 'kill $sampler 2>/dev/null' EXIT

# 1. data, every core
cores=$(nproc)
stage data-smoke 120 "${sb[@]}" data synthtown --preset smoke --out "$W/data/smoke" --quiet
[ "$SMALL" = smoke ] || stage data-small 240 "${sb[@]}" data synthtown --preset "$SMALL" --out "$W/data/$SMALL" --workers "$cores" --quiet

# 2. every method's smoke on CUDA, 5 at a time, each in its own cache and output
methods=${METHODS:-$(python3 -c "from reference.methods import METHODS; print(' '.join(sorted(METHODS)))")}
smoke_one() {
  local m=$1 dev=(--device "$DEVICE")
  [ "$m" = mean-frame ] && dev=()  # the floor runs on the CPU only
  local t0=$SECONDS
  SKYEYES_CACHE=$W/cache-$m timeout 300 python3 -m skyeyes_bench.cli reproduce --method "$m" --preset smoke \
    "${dev[@]}" --data "$W/data/smoke" --out "$W/smoke/$m" --quiet --force > "$W/smoke-$m.log" 2>&1
  local rc=$?
  printf 'smoke %-15s rc=%d %4ds  %s\n' "$m" "$rc" $((SECONDS - t0)) "$(grep -m1 -E '^ *(lpips|fid|psnr)' "$W/smoke-$m.log" | tr -s ' ')"
  [ $rc = 0 ] || tail -5 "$W/smoke-$m.log"
  return $rc
}
export -f smoke_one
export W DEVICE
t0=$SECONDS
printf '%s\n' $methods | xargs -P 5 -I{} bash -c 'smoke_one {}'
printf 'smokes\t%d\t%d\n' $((SECONDS - t0)) $? | tee -a "$stages"

# 3. skyeyes small end to end on CUDA (data already generated: not counted)
stage skyeyes-small 480 "${sb[@]}" reproduce --method skyeyes --preset "$SMALL" --device "$DEVICE" --data "$W/data/$SMALL" \
  --out "$W/skyeyes-small" --quiet --force
run=$W/skyeyes-small
python3 - "$run" "$W/gpumem.log" <<'EOF' | tee "$OUT/skyeyes-small-summary.json"
import glob, json, sys
run, mem = sys.argv[1], sys.argv[2]
out = {}
for f in glob.glob(f"{run}/work/*/method/training.json"):
    out["training"] = {k: {x: v.get(x) for x in ("steps", "seconds", "it_per_s", "device", "mixed_precision",
                                                  "processes", "final_loss")} for k, v in json.load(open(f)).items()}
priors = [json.load(open(f)) for f in glob.glob(f"{run}/work/*/method/prior/scenes/*/fit.json")]
out["prior_lanes"] = {"n": len(priors), "fit_seconds": sorted(round(p.get("fit_seconds", 0), 1) for p in priors)}
try:
    sub = json.load(open(f"{run}/submission/submission.json"))
    out["timings"] = {k: v for k, v in sub.get("timings", {}).items() if k != "per_frame_render_s"}
    out["hardware"] = sub.get("hardware")
    out["config"] = {k: sub.get("config", {}).get(k) for k in ("acm_steps", "acm_batch", "vcm_steps", "vcm_batch",
                                                              "mixed_precision", "device")}
except OSError as e:
    out["submission"] = f"missing: {e}"
try:
    out["peak_gpu_memory_mb"] = max(int(x) for x in open(mem).read().split() if x.strip().isdigit())
except (OSError, ValueError):
    out["peak_gpu_memory_mb"] = None
print(json.dumps(out, indent=1))
EOF

# 4. the submission, packed for scoring elsewhere (15 MB parts; the first 3 come back with this
# run, the rest with `bash scripts/gpu-check.sh more`)
if [ -f "$run/submission/submission.json" ]; then
  rm -f "$W"/skyeyes-small.tar.part-*
  tar -C "$run" -cf - submission | split -b 15M -d - "$W/skyeyes-small.tar.part-"
  ls "$W"/skyeyes-small.tar.part-* | head -n 3 | xargs -r cp -t "$OUT"
  n=$(ls "$W"/skyeyes-small.tar.part-* | wc -l)
  echo "submission: $n part(s) of 15 MB; $((n > 3 ? n - 3 : 0)) left for 'bash scripts/gpu-check.sh more'"
fi
echo "== stages (seconds):"; cat "$stages"
