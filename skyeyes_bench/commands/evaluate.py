"""`skyeyes-bench evaluate SUBMISSION`: score a submission against its protocol."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("evaluate", help="score a submission (validate, metrics, intervals -> results.json)",
                       description="Validate a submission (every problem listed, exit 2, nothing written), "
                       "then compute the metrics its protocol asks for with clustered-bootstrap intervals "
                       "and write results JSON plus a .features.npz sidecar.")
    p.add_argument("submission", metavar="SUBMISSION", help="submission folder (holds submission.json)")
    p.add_argument("--data", metavar="DIR", help="dataset folder (default: from submission.json and the "
                   "protocol's default location)")
    p.add_argument("--out", metavar="FILE", help="results file (default: SUBMISSION.results.json beside "
                   "the folder, or SUBMISSION.shard-I-of-N.results.json)")
    p.add_argument("--shard", metavar="I/N", help="evaluate only sequences k with k %% N == I; write a "
                   "partial result for `skyeyes-bench merge`")
    p.add_argument("--force", action="store_true", help="replace an existing results file")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--json", action="store_true", help="print the results JSON instead of a summary")
    p.set_defaults(handler="skyeyes_bench.commands._evaluate_impl:evaluate_cmd")
