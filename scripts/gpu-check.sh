#!/usr/bin/env bash
# The one prepared check of the reference side on a bare GPU machine (issue 34; docs/gpu.md).
#
# The machine has PyTorch with CUDA and no network. What else the project needs comes as wheels
# in .whl/ beside the checkout (`bash scripts/gpu-wheels.sh`, run where there is network); the
# SynthTown data may come along in .gpu-data/ (`bash scripts/gpu-check.sh pack-data`, here), which
# spares the GPU machine the minute that generating it takes. From the repository root:
#
#   bash scripts/gpu-check.sh          # all: start, then finish, in one go (a machine without a time limit)
#   bash scripts/gpu-check.sh start    # first device run: the jobs below, in their own session
#   bash scripts/gpu-check.sh finish   # second device run, on the same warm machine: wait, pack, hand back
#   bash scripts/gpu-check.sh tests    # the test suite's `gpu` tests (not slow), on their own
#   bash scripts/gpu-check.sh seeds    # first device run of a seeds check (below); then `finish`, once
#                                      # per submission: each call hands back one
#
# A lent machine runs one command for at most 10 minutes, so `start` launches the jobs with
# setsid (they outlive the command) and watches them for MONITOR_S seconds; `finish`, called at
# once on the same warm machine, watches them until FINISH_S and hands back what they wrote. The
# jobs, in order:
#   0. (BENCH=1) the ACM training step of `small` at batch 32, bf16, eager and under torch.compile
#      (COMPILE_MODE, default reduce-overhead: CUDA graphs), 100 steps each: `small` below runs
#      with `--set compile=MODE` where that is more than 20% faster;
#   1. Skyeyes `small` end to end on CUDA (`reproduce --device cuda`), alone on the machine, timed
#      (data not counted), with each stage's seconds and the peak GPU memory over all processes;
#   2. when it ends, or SMOKE_AT seconds after it started, all at once: the README's first command
#      as written (`reproduce --method skyeyes --preset smoke`, device "auto", default data and
#      cache), `reproduce --preset smoke --device cuda` of every other method (the floor on the
#      CPU: it has no device), each with its own cache, and the `gpu` tests;
#   3. the small submission packed as a tar in 15 MiB parts, for scoring where the metric weights
#      are: `cat skyeyes-small.tar.part-* | tar -x -C run/`, then `skyeyes-bench evaluate`.
# What comes back ($OUT, default ./gpu-check-out; a lent machine hands back at most 8 files, 64 MiB):
# gpu-check.log (this command), jobs.log (the jobs'), stages.tsv (name, seconds, rc, start offset),
# skyeyes-small-summary.json and up to 4 tar parts: one packed submission a call, the next one not
# yet handed back.
# `seeds` (issue 57: the seed spread of the paper's VCM ablation) runs, for each seed of SEEDS
# (default "0 1 2 3 4": the GPU rows' own seeds), each method of SEED_METHODS (default "skyeyes
# skyeyes-no-vcm": one stage cache, so a seed's ACM is trained once for both) at `small` on CUDA, one after the other, and packs each
# submission as it ends (name <method>-seed-<s>); seeds-summary.json holds every run's stages and
# timings. Scored here, each into its row's seed folder, then combined:
#   cat skyeyes-seed-1.tar.part-* | tar -x -C gpu/skyeyes/seed-1/
#   skyeyes-bench evaluate gpu/skyeyes/seed-1/submission --out gpu/skyeyes/seed-1/results.json
#   skyeyes-bench seeds gpu/skyeyes        # gpu/skyeyes/results.json with the seeds' spread
# A dry run of the plumbing on a CPU machine:
#   DEVICE=cpu BENCH=0 SMALL=smoke SMALL_ARGS="--set acm_steps=20 --set vcm_steps=4" METHODS="mean-frame" \
#     GPU_TESTS=0 SMOKE_AT=60 bash scripts/gpu-check.sh
# (METHODS: the smokes, default "readme" and every method but skyeyes; SMALL_ARGS: extra arguments
# of the timed run.)
set -uo pipefail
cd "$(dirname "$0")/.."
mode=${1:-all}
DEVICE=${DEVICE:-cuda}          # cpu: a dry run of this script's plumbing where there is no GPU
SMALL=${SMALL:-small}           # the preset timed end to end (smoke for a dry run)
OUT=${OUT:-$PWD/gpu-check-out}
W=${GPU_CHECK_WORK:-/tmp/skyeyes-gpu-check}  # outside the checkout: a second run's fresh copy of the tree leaves it be
SMOKE_AT=${SMOKE_AT:-300}       # the smokes start when small ends, or this many seconds after it started
MONITOR_S=${MONITOR_S:-570}     # `start` returns this many seconds after it began
FINISH_S=${FINISH_S:-100000}    # `finish` returns after this many seconds (or when every job has ended)
GPU_TESTS=${GPU_TESTS:-1}
BENCH=${BENCH:-1}               # time the ACM step eager and compiled first; small takes the faster
COMPILE_MODE=${COMPILE_MODE-reduce-overhead}
BENCH_ARGS=${BENCH_ARGS:---steps 100 --warmup 20 --frames 16}
SEEDS=${SEEDS:-0 1 2 3 4}       # seeds mode: the seeds, and the methods run for each
SEED_METHODS=${SEED_METHODS:-skyeyes skyeyes-no-vcm}
mkdir -p "$OUT" "$W"
export PYTHONUNBUFFERED=1 TQDM_DISABLE=1

if [ "$mode" = pack-data ]; then  # here: the data the jobs use, generated once, into .gpu-data/ (carried)
  sb=(.venv/bin/skyeyes-bench data synthtown --quiet)
  mkdir -p .gpu-data
  grep -qx '/.gpu-data/' .git/info/exclude 2>/dev/null || echo '/.gpu-data/' >> .git/info/exclude
  [ -d .gpu-data/smoke ] || "${sb[@]}" --preset smoke --out .gpu-data/smoke || exit 1
  [ -d ".gpu-data/$SMALL" ] || "${sb[@]}" --preset "$SMALL" --out ".gpu-data/$SMALL" --workers "$(nproc)" || exit 1
  du -sh .gpu-data/*
  exit 0
fi

exec > >(tee -a "$OUT/gpu-check.log") 2>&1
site=/tmp/skyeyes-site
SRC=$W/src
export PYTHONPATH=$site:$SRC SKYEYES_CACHE=$W/cache
stages=$W/stages.tsv
t_start() { date +%s > "$W/t0"; }
since() { echo $(( $(date +%s) - $(cat "$W/t0" 2>/dev/null || date +%s) )); }
stamp() {  # stamp TAG: each line read, prefixed with the seconds since the timed run's start and TAG
  local l; while IFS= read -r l; do printf '+%ss %s %s\n' "$(since)" "$1" "$l"; done
}

stage() {  # stage NAME SECONDS_LIMIT CMD...: run, time, record "name seconds rc start"
  local name=$1 limit=$2; shift 2
  local t0=$SECONDS at; at=$(since)
  timeout "$limit" "$@"; local rc=$?
  printf '%s\t%d\t%d\t%d\n' "$name" $((SECONDS - t0)) "$rc" "$at" >> "$stages"
  return $rc
}

summary() {  # summary MODE MEMLOG RUN...: each run's stage seconds, devices, lanes and scores, and peak memory, as JSON
  python3 - "$@" <<'EOF'
import glob, json, sys
mode, mem, runs = sys.argv[1], sys.argv[2], sys.argv[3:]


def one(run):
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
                                                                  "mixed_precision", "device", "components")}
    except OSError as e:
        out["submission"] = f"missing: {e}"
    try:
        res = json.load(open(f"{run}/results.json"))
        out["scores"] = {k: v.get("value") if isinstance(v, dict) else v for k, v in res.get("metrics", {}).items()}
    except (OSError, ValueError, AttributeError):
        pass
    return out


# seeds mode: every run by name (<method>-seed-<s>, from $W/seeds/<method>/seed-<s>)
out = {"runs": {r.split("/seeds/")[-1].replace("/", "-"): one(r) for r in runs}} if mode == "seeds" else one(runs[0])
try:
    out["peak_gpu_memory_mb"] = max(int(x) for x in open(mem).read().split() if x.strip().isdigit())
except (OSError, ValueError):
    out["peak_gpu_memory_mb"] = None
print(json.dumps(out, indent=1))
EOF
}

pack() {  # pack NAME RUN: RUN's submission as 15 MiB tar parts in the hand-back queue
  local name=$1 run=$2
  [ -f "$run/submission/submission.json" ] || { echo "submission $name: none written"; return 0; }
  mkdir -p "$W/queue"
  tar -C "$run" -cf - submission | split -b 15M -d - "$W/queue/$name.tar.part-" && touch "$W/queue/$name.ready"
  echo "submission $name: $(ls "$W/queue/$name".tar.part-* | wc -l) part(s) of 15 MiB ($(du -sh "$run/submission" | cut -f1))"
}

handback() {  # copy what the jobs wrote so far into $OUT (a rename, so no half file comes back)
  local f cur n
  for f in stages.tsv jobs.log; do [ -f "$W/$f" ] && cp "$W/$f" "$OUT/$f.part" && mv "$OUT/$f.part" "$OUT/$f"; done
  if [ "$(cat "$W/mode" 2>/dev/null)" = seeds ]; then
    summary seeds "$W/gpumem.log" "$W"/seeds/*/seed-* > "$OUT/seeds-summary.json.part" 2>/dev/null \
      && mv "$OUT/seeds-summary.json.part" "$OUT/seeds-summary.json"
  else
    summary small "$W/gpumem.log" "$W/skyeyes-small" > "$OUT/skyeyes-small-summary.json.part" 2>/dev/null \
      && mv "$OUT/skyeyes-small-summary.json.part" "$OUT/skyeyes-small-summary.json"
  fi
  # one packed submission a call (a call hands back at most 64 MiB): the one this call took, else
  # the first not yet handed back by an earlier call
  cur=$(cat "$W/queue/this-call" 2>/dev/null)
  if [ -z "$cur" ]; then
    for f in $(ls "$W"/queue/*.ready 2>/dev/null); do
      n=$(basename "$f" .ready); [ -f "$W/queue/$n.sent" ] || { cur=$n; break; }
    done
    [ -n "$cur" ] && { echo "$cur" > "$W/queue/this-call"; touch "$W/queue/$cur.sent"; echo "handing back $cur"; }
  fi
  [ -n "$cur" ] || return 0
  for f in $(ls "$W/queue/$cur".tar.part-* | head -n 4); do
    [ -f "$OUT/$(basename "$f")" ] || { cp "$f" "$OUT/x.part" && mv "$OUT/x.part" "$OUT/$(basename "$f")"; }
  done
}

watch_jobs() {  # watch_jobs SECONDS: print the stage table as it grows; hand back every 15 s
  local until=$(( $(date +%s) + $1 )) shown=0 n
  while [ "$(date +%s)" -lt "$until" ]; do
    n=$(wc -l < "$stages" 2>/dev/null || echo 0)
    [ "$n" -gt "$shown" ] && { tail -n +$((shown + 1)) "$stages" | sed 's/^/stage: /'; shown=$n; }
    handback
    [ -f "$W/done" ] && { echo "jobs: all ended at +$(since) s"; break; }
    sleep 15
  done
  [ -f "$W/done" ] || echo "jobs: still running at +$(since) s: $(ls "$W"/running-* 2>/dev/null | sed 's/.*running-//' | tr '\n' ' ')"
  handback
  nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv,noheader 2>/dev/null || true
}

smoke_one() {  # smoke_one METHOD: its smoke on $DEVICE, own cache and output; the README's command for skyeyes
  local m=$1 t0=$SECONDS cmd
  if [ "$m" = readme ]; then  # as written: no --device, --data or --out
    cmd=(python3 -m skyeyes_bench.cli reproduce --method skyeyes --preset smoke --quiet)
  else
    cmd=(python3 -m skyeyes_bench.cli reproduce --method "$m" --preset smoke --data "$W/data/smoke" --out "$W/smoke/$m" --quiet)
    [ "$m" = mean-frame ] || cmd+=(--device "$DEVICE")  # the floor runs on the CPU only
  fi
  touch "$W/running-$m"
  (cd "$SRC" && SKYEYES_CACHE=$W/cache-$m timeout 420 "${cmd[@]}") 2>&1 | stamp "$m" > "$W/smoke-$m.log"
  local rc=${PIPESTATUS[0]}
  printf 'smoke-%s\t%d\t%d\t%d\n' "$m" $((SECONDS - t0)) "$rc" "$(since)" >> "$stages"
  { echo "== smoke $m rc=$rc $((SECONDS - t0)) s"; grep -E ' (psnr|ssim|warp) |: steps |steps in|Error|error' "$W/smoke-$m.log" | grep -v unavailable | head -12
    [ $rc = 0 ] || tail -25 "$W/smoke-$m.log"; } >> "$W/jobs.log"
  rm -f "$W/running-$m"
}

jobs_main() {  # runs in its own session (setsid): small, then the smokes and tests, then the pack
  exec >> "$W/jobs.log" 2>&1
  cd "$SRC"
  nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -lms 500 > "$W/gpumem.log" 2>/dev/null &
  local sampler=$!
  local small_args=$SMALL_ARGS
  if [ "$BENCH" = 1 ]; then  # the ACM step (batch 32, bf16) eager and compiled; small takes the faster
    stage step-bench 300 python3 bench/diffusion_step.py --device "$DEVICE" --batch 32 --precision bf16 \
      --compile ",$COMPILE_MODE" $BENCH_ARGS --out "$W/step-bench.json" 2>&1 | stamp bench
    local pick
    pick=$(python3 -c "import json,sys; r=json.load(open(sys.argv[1])); b=min(r, key=lambda x: x['s_per_step']); print(b['compile'] if b['s_per_step'] < 0.8 * r[0]['s_per_step'] else '')" "$W/step-bench.json" 2>/dev/null)
    [ -n "$pick" ] && small_args="--set compile=$pick $small_args"
    echo "small runs with: ${small_args:-the preset as it is}"
  fi
  rm -rf "$W/skyeyes-small"  # a fresh run: an earlier check's stage cache and submission would be read as this one's
  t_start  # small's seconds count from here
  touch "$W/running-small"
  (stage skyeyes-small 1500 python3 -m skyeyes_bench.cli reproduce --method skyeyes --preset "$SMALL" \
     --device "$DEVICE" --data "$W/data/$SMALL" --out "$W/skyeyes-small" --quiet --force $small_args 2>&1 | stamp small
   pack skyeyes-small "$W/skyeyes-small"
   rm -f "$W/running-small") &
  local small=$!
  while kill -0 $small 2>/dev/null && [ "$(since)" -lt "$SMOKE_AT" ]; do sleep 2; done
  echo "smokes start at +$(since) s (small $(kill -0 $small 2>/dev/null && echo 'still running' || echo ended))"
  local methods=${METHODS:-readme $(python3 -c "from reference.methods import METHODS; print(' '.join(sorted(set(METHODS) - {'skyeyes'})))")}
  local pids=()
  for m in $methods; do smoke_one "$m" & pids+=($!); done
  if [ "$GPU_TESTS" = 1 ]; then
    (touch "$W/running-tests"
     stage gpu-tests 420 python3 -m pytest -q -p no:cacheprovider -m "gpu and not slow" tests > "$W/tests.log" 2>&1
     { echo "== gpu tests"; tail -30 "$W/tests.log"; } >> "$W/jobs.log"; rm -f "$W/running-tests") & pids+=($!)
  fi
  wait "${pids[@]}" $small
  kill $sampler 2>/dev/null
  echo "jobs ended at +$(since) s"
  touch "$W/done"
}

jobs_seeds() {  # seeds mode, in its own session: each seed's methods at $SMALL on $DEVICE, each packed as it ends
  exec >> "$W/jobs.log" 2>&1
  cd "$SRC"
  nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -lms 500 > "$W/gpumem.log" 2>/dev/null &
  local sampler=$! s m name
  t_start
  for s in $SEEDS; do
    for m in $SEED_METHODS; do  # one cache: the seed's priors and ACM are made by its first method, read by the rest
      name=$m-seed-$s
      touch "$W/running-$name"
      stage "$name" 1500 python3 -m skyeyes_bench.cli reproduce --method "$m" --preset "$SMALL" --seed "$s" \
        --device "$DEVICE" --data "$W/data/$SMALL" --out "$W/seeds/$m/seed-$s" --quiet --force $SMALL_ARGS 2>&1 | stamp "$name"
      pack "$name" "$W/seeds/$m/seed-$s"
      rm -f "$W/running-$name"
    done
  done
  kill $sampler 2>/dev/null
  echo "jobs ended at +$(since) s"
  touch "$W/done"
}

case $mode in
  start|all|seeds)
    echo "== gpu-check $mode at $(git rev-parse --short HEAD 2>/dev/null || echo '?') on $(hostname), $(date -u +%FT%TZ)"
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || echo "no nvidia-smi"
    if ls .whl/*.whl >/dev/null 2>&1 && [ ! -d "$site" ]; then  # the wheels, aside from the image's own environment
      python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$site" .whl/*.whl \
        || { echo "gpu-check: installing .whl/*.whl failed"; exit 1; }
    fi
    rm -rf "$SRC" "$W"/done "$W"/queue "$W"/seeds "$W"/running-* "$stages" "$W/jobs.log"
    echo "$mode" > "$W/mode"  # what `finish` hands back: the small run's, or the seeds'
    mkdir -p "$SRC" "$W/data"
    tar --exclude=./.whl --exclude=./.gpu-data --exclude=./.git --exclude=./.venv --exclude=./outputs --exclude=./gpu-check-out -cf - . | tar -C "$SRC" -xf -
    python3 -c "import os, torch, diffusers; print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'no GPU', '| diffusers', diffusers.__version__, '| cores', os.cpu_count())"
    printf 'stage\tseconds\trc\tstart\n' > "$stages"
    t_start
    presets="smoke $SMALL"; [ "$mode" = seeds ] && presets=$SMALL
    for p in $presets; do  # the carried data, or generated here with every core (not counted in small's time)
      if [ -d ".gpu-data/$p" ]; then cp -a ".gpu-data/$p" "$W/data/$p"
      else stage "data-$p" 300 python3 -m skyeyes_bench.cli data synthtown --preset "$p" --out "$W/data/$p" --workers "$(nproc)" --quiet; fi
    done
    t_start  # the stage offsets count from the timed run's start
    export -f stage since stamp t_start smoke_one pack jobs_main jobs_seeds
    export W SRC DEVICE SMALL SMOKE_AT GPU_TESTS BENCH COMPILE_MODE BENCH_ARGS SEEDS SEED_METHODS stages METHODS=${METHODS:-} SMALL_ARGS=${SMALL_ARGS:-}
    if [ "$mode" = seeds ]; then setsid bash -c jobs_seeds < /dev/null > /dev/null 2>&1 &
    else setsid bash -c jobs_main < /dev/null > /dev/null 2>&1 &
    fi
    if [ "$mode" != all ]; then watch_jobs $((MONITOR_S - SECONDS)); exit 0; fi
    watch_jobs "$FINISH_S";;
  finish)
    echo "== gpu-check finish at +$(since) s"
    rm -f "$W/queue/this-call"  # this call hands back the next packed submission
    watch_jobs "$FINISH_S";;
  tests)
    (cd "$SRC" 2>/dev/null || cd .; stage gpu-tests 540 python3 -m pytest -q -p no:cacheprovider -m "gpu and not slow" tests);;
  *) echo "usage: bash scripts/gpu-check.sh [all|start|finish|seeds|tests|pack-data]"; exit 2;;
esac
[ -f "$W/done" ] && { echo "== stages (seconds):"; column -t "$stages" 2>/dev/null || cat "$stages"; }
exit 0
