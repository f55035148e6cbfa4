"""Scoring a submission, in small pieces (`skyeyes_bench.evaluate` re-exports what callers use):

* `inputs`: the inputs of a run and the checks before any scoring (`open_inputs`, `check_out`,
  `check_extractors`, `missing_metrics`, `MissingMetrics`);
* `context`: `ScoringRun`, what one run scores and what it records (timing, unavailable metrics,
  the per-frame records);
* `frames`: the frame metrics, frame by frame and a sequence at a time (depth, poses);
* `features`: the features of the set metrics (cached), and `clips`, how sequences are cut into clips;
* `run`: `evaluate`, the stages in order, and the partial / results document.

Which metrics exist and which function computes each comes from `metricspec`; the results file
from `results`, the summary and the set metrics from `summary.finalize`.
"""
