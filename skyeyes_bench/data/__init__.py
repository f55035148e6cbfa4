"""The canonical dataset layout (see DESIGN.md) and the tools that write it.

Names load lazily: `skyeyes_bench.commands.data` imports submodules of this package while
building the CLI parser, which must not pull in numpy or OpenImageIO.
"""

from __future__ import annotations

import importlib

__all__ = ["Dataset", "DatasetWriter", "Frame", "Scene", "Sequence", "open_dataset", "validate_dataset"]


def __getattr__(name: str):
    if name in __all__:
        return getattr(importlib.import_module("skyeyes_bench.data.layout"), name)
    raise AttributeError(f"module 'skyeyes_bench.data' has no attribute {name!r}")
