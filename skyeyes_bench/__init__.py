"""skyeyes-bench: benchmark and reference methods for aerial-to-ground view synthesis.

Imports here are lazy so that `skyeyes-bench --help` stays instant; the heavy modules
(torch, OpenImageIO) load on first use of the names below.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

_LAZY = {
    "load_protocol": "skyeyes_bench.protocol:load_protocol",
    "Protocol": "skyeyes_bench.protocol:Protocol",
    "Camera": "skyeyes_bench.cameras:Camera",
    "Dataset": "skyeyes_bench.data.layout:Dataset",
    "open_dataset": "skyeyes_bench.data.layout:open_dataset",
    "UserError": "skyeyes_bench.errors:UserError",
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        module, attr = _LAZY[name].split(":")
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'skyeyes_bench' has no attribute {name!r}")
