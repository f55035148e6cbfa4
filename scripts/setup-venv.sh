#!/usr/bin/env bash
# Create (or update) the project's virtual environment in .venv.
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
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi
.venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip 2>&1 | grep -v "^WARNING: Location" || true
.venv/bin/python -m pip install -q --disable-pip-version-check "torch==2.13.0" 2>&1 | grep -v "^WARNING: Location" || true
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[dev,reference]" 2>&1 | grep -v "^WARNING: Location" || true
.venv/bin/python -c "import torch, skyeyes_bench" >/dev/null
echo "$want" > "$stamp"
