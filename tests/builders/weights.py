"""The real extractor weights in tests: where `skyeyes-bench weights fetch` put them, linking
them into a test's isolated cache, and skipping (locally) or failing (CI) when they are absent.

CI sets SKYEYES_REQUIRE_WEIGHTS=1 (.ci/run): then tests/conftest.py turns every skip whose
reason names the fixing command `FIX` into a failure, so a CI run that could not fetch the
weights cannot pass with no Inception, LPIPS or I3D check at all.
"""

import os

import pytest

from skyeyes_bench import paths
from skyeyes_bench.metrics import weights as W

#: Resolved at import (collection), before conftest's per-test cache isolation: the user's cache.
REAL_DIR = paths.weights_dir()
#: The command that fixes a missing weight file (the conftest hook looks for it in skip reasons).
FIX = "skyeyes-bench weights fetch"
#: The switch that makes missing weights a failure (set by .ci/run).
REQUIRE_ENV = "SKYEYES_REQUIRE_WEIGHTS"


def required() -> bool:
    return os.environ.get(REQUIRE_ENV, "") not in ("", "0")


def have(name: str) -> bool:
    """The file is in REAL_DIR with the sha256 skyeyes_bench expects."""
    p = REAL_DIR / name
    return p.is_file() and W.sha256_file(p) == W.WEIGHT_FILES[name].sha256


def missing_reason(*names: str) -> str | None:
    """Why a test needing `names` cannot run (with the fixing command), or None."""
    gone = [n for n in names if not have(n)]
    if not gone:
        return None
    return f"{', '.join(gone)} absent from {REAL_DIR}: run `{FIX}`"


def needs(*names: str):
    """A skipif marker for tests needing the real weight files `names`."""
    reason = missing_reason(*names)
    return pytest.mark.skipif(reason is not None, reason=reason or "")


def link_real_weights(*names: str) -> None:
    """Symlink the real weight files into the current (test-isolated) weights dir."""
    d = paths.weights_dir()
    d.mkdir(parents=True, exist_ok=True)
    for name in names:
        if (REAL_DIR / name).is_file() and not (d / name).exists():
            (d / name).symlink_to(REAL_DIR / name)


def require(*names: str) -> None:
    """Skip the running test (a failure under SKYEYES_REQUIRE_WEIGHTS=1) unless `names` are
    present; then link them into its cache."""
    reason = missing_reason(*names)
    if reason:
        pytest.skip(reason)
    link_real_weights(*names)
