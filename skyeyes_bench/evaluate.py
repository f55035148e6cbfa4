"""Score a submission: validate, per-frame metrics, features; then `summary.finalize` adds the
set metrics and statistics and writes the results file.

The module is callable: `skyeyes_bench.evaluate("sub/", ...)` is `skyeyes_bench.api.evaluate`,
the public entry point (strict about missing metrics, no progress bars, writes nothing unless
`out=` is given; docs/evaluate.md, "Python API"). Below, the internal function it calls:

```
results = evaluate("sub/", data=None, out="results.json")          # whole test split
part = evaluate("sub/", out="part-0.json", shard=(0, 4))          # sequences 0, 4, 8, ...
results = merge(["part-0.json", ...], out="results.json")          # == the unsharded numbers
```

The pieces live in `skyeyes_bench.scoring` (the inputs and checks, `ScoringRun`, the frame
metrics, the features, the stages in order); which metrics exist and which function computes
each comes from `metricspec`; the results file format (and `read_results`, ...) from `results`,
`finalize` from `summary` and `merge` from `shards`, all re-exported here.
"""

from __future__ import annotations

import sys
import types

from .results import (  # noqa: F401  (re-exported: callers import these from evaluate)
    FEATURES_OUTPUT, PARTIAL_FORMAT, RESULTS_FORMAT, RESULTS_OUTPUT, default_out, features_path, lines_digest,
    progress_bar, read_results, timed_stage, write_results)
from .scoring.inputs import (  # noqa: F401  (re-exported)
    MissingMetrics, builtin_protocol_ids, check_extractors, check_out, missing_metrics, open_inputs, parse_shard,
    resolve_data)
from .scoring.run import evaluate  # noqa: F401  (re-exported)
from .shards import merge  # noqa: F401  (re-exported)
from .summary import finalize, format_summary  # noqa: F401  (re-exported)


class _CallableModule(types.ModuleType):
    """This module, callable as `api.evaluate`. `skyeyes_bench.evaluate` names both this module and
    the public function (importing a submodule sets the package's attribute to it, whatever
    `skyeyes_bench.__init__` offered), so the module answers the call itself."""

    def __call__(self, submission, data=None, **kwargs):
        from .api import evaluate as public

        return public(submission, data, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
