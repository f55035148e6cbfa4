"""Where things live: the cache (weights, features, generated data) and the protocol files."""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir() -> Path:
    """`$SKYEYES_CACHE`, else `~/.cache/skyeyes-bench`."""
    env = os.environ.get("SKYEYES_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "skyeyes-bench"


def data_dir() -> Path:
    """Generated datasets (SynthTown) live under the cache: `<cache>/data/<name>`."""
    return cache_dir() / "data"


def weights_dir() -> Path:
    return cache_dir() / "weights"


def features_dir() -> Path:
    return cache_dir() / "features"


def protocols_dir() -> Path:
    """`$SKYEYES_PROTOCOLS`, else the shipped protocols (`builtin_protocols_dir`)."""
    env = os.environ.get("SKYEYES_PROTOCOLS")
    if env:
        return Path(env)
    return builtin_protocols_dir()


def builtin_protocols_dir() -> Path:
    """The protocols shipped with skyeyes-bench, whatever `$SKYEYES_PROTOCOLS` says: the copy
    inside an installed wheel, else the repository's (may not exist)."""
    packaged = Path(__file__).parent / "_protocols"
    if packaged.is_dir():
        return packaged
    return Path(__file__).resolve().parent.parent / "protocols"


def repo_root() -> Path | None:
    """The source checkout (editable installs), or None for an installed wheel."""
    root = Path(__file__).resolve().parent.parent
    return root if (root / "pyproject.toml").is_file() else None
