import io
import os
from pathlib import Path

import pytest

# Imported before any test isolates its cache: REAL_DIR is where `weights fetch` put the weights.
from builders import weights as _real_weights  # noqa: F401

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(autouse=True)
def _isolated_cache(tmp_path_factory, monkeypatch):
    """Each test gets its own cache dir unless it asks otherwise (no writes to ~/.cache)."""
    if "SKYEYES_TEST_SHARED_CACHE" not in os.environ:
        monkeypatch.setenv("SKYEYES_CACHE", str(tmp_path_factory.mktemp("cache")))
    yield


@pytest.fixture(autouse=True)
def _fresh_extractors_under_mutation():
    """Under bench/mutation.py (SKYEYES_MUTATION=1) every test loads its extractors' networks
    itself: mutmut maps a mutant to the tests that ran its function, and a network loaded by an
    earlier test in the same process would hide its constructor from the later ones."""
    if os.environ.get("SKYEYES_MUTATION"):
        from skyeyes_bench.metrics import extractors

        extractors._INSTANCES.clear()
    yield


class _TTYStringIO(io.StringIO):
    def isatty(self) -> bool:
        return True


def run_cli(*args: str, check: int | None = 0, tty: bool = False):
    """Run `skyeyes-bench ARGS` in-process; return (rc, stdout, stderr). tty=True: stderr says it
    is a terminal (progress bars are drawn only there)."""
    import contextlib

    from skyeyes_bench.cli import main

    out, err = io.StringIO(), (_TTYStringIO() if tty else io.StringIO())
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main(list(args))
        except SystemExit as e:  # argparse
            rc = e.code if isinstance(e.code, int) else 2
    if check is not None:
        assert rc == check, f"rc={rc}\nstdout:\n{out.getvalue()}\nstderr:\n{err.getvalue()}"
    return rc, out.getvalue(), err.getvalue()


@pytest.fixture(scope="session")
def synthtown_smoke(tmp_path_factory) -> Path:
    """The SynthTown `smoke` dataset, generated once per test session (read-only: don't modify)."""
    from skyeyes_bench.data.synthtown import generate_dataset

    out = tmp_path_factory.mktemp("synthtown") / "synthtown-smoke"
    return generate_dataset(out, preset="smoke", seed=0, progress=False)


@pytest.fixture
def one_torch_thread():
    """One torch thread: on a shared 2-core machine a second OpenMP thread made small ops ~50x
    slower (spin-waiting under contention). Restored after the test."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def pytest_collection_modifyitems(config, items):
    """Tests marked `gpu` run wherever CUDA is present and are skipped, with that reason, elsewhere."""
    gpu = [item for item in items if "gpu" in item.keywords]
    if not gpu:
        return
    import torch

    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA GPU (torch.cuda.is_available() is False here)")
    for item in gpu:
        item.add_marker(skip)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """Under SKYEYES_REQUIRE_WEIGHTS=1 (CI), a skip for missing weights is a failure: its reason
    names `skyeyes-bench weights fetch` (builders.weights.FIX). Locally such tests still skip."""
    outcome = yield
    rep = outcome.get_result()
    if not rep.skipped:
        return
    from builders.weights import FIX, REQUIRE_ENV, required

    reason = rep.longrepr[2] if isinstance(rep.longrepr, tuple) else str(rep.longrepr)
    if required() and FIX in reason:
        rep.outcome = "failed"
        rep.longrepr = f"{REQUIRE_ENV}=1 and the real weights are missing: {reason}"
