"""skyeyes-bench: benchmark and reference methods for aerial-to-ground view synthesis.

The Python API (`skyeyes_bench.api`, docs/evaluate.md "Python API"), plain values out:

    import skyeyes_bench as sb
    res = sb.evaluate("sub/")                         # results dict, as `evaluate --json`
    cmp = sb.compare("a.results.json", "b.results.json")   # as `compare --json`
    fid = sb.compute_fid("frames_a/", "frames_b/")    # float; also compute_kid/_fvd/_kvd/_lpips

Imports here are lazy so that `skyeyes-bench --help` stays instant; the heavy modules
(numpy, torch, OpenImageIO) load on first use of the names below.
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
    "ValidationError": "skyeyes_bench.errors:ValidationError",
    "MissingMetrics": "skyeyes_bench.scoring.inputs:MissingMetrics",
    # the Python API (skyeyes_bench.api)
    "compare": "skyeyes_bench.api:compare",
    "compute_fid": "skyeyes_bench.api:compute_fid",
    "compute_kid": "skyeyes_bench.api:compute_kid",
    "compute_fvd": "skyeyes_bench.api:compute_fvd",
    "compute_kvd": "skyeyes_bench.api:compute_kvd",
    "compute_lpips": "skyeyes_bench.api:compute_lpips",
    "folder_metrics": "skyeyes_bench.api:folder_metrics",
}

__all__ = ["__version__", "evaluate", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        module, attr = _LAZY[name].split(":")
        return getattr(importlib.import_module(module), attr)
    if name == "evaluate":
        # `skyeyes_bench.evaluate` is also the module of that name, and importing a submodule sets
        # the package's attribute to the module: so the module itself is callable (its `__call__`
        # is `api.evaluate`), and `sb.evaluate("sub/")` scores a submission whichever was loaded first.
        return importlib.import_module("skyeyes_bench.evaluate")
    raise AttributeError(f"module 'skyeyes_bench' has no attribute {name!r}")
