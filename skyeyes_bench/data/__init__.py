"""The canonical dataset layout (docs/formats.md) and the tools that write it.

Names load lazily: importing a submodule (e.g. `skyeyes_bench.data.synthtown.presets`) must not
pull in numpy or OpenImageIO.
"""

from __future__ import annotations

import importlib

__all__ = ["Dataset", "DatasetWriter", "Frame", "Scene", "Sequence", "open_dataset", "validate_dataset"]


def __getattr__(name: str):
    if name in __all__:
        module = "writer" if name == "DatasetWriter" else "layout"
        return getattr(importlib.import_module(f"skyeyes_bench.data.{module}"), name)
    raise AttributeError(f"module 'skyeyes_bench.data' has no attribute {name!r}")
