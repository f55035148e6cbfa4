"""`skyeyes-bench evaluate SUBMISSION`: score a submission against its protocol."""

from __future__ import annotations

import json


def register(sub) -> None:
    p = sub.add_parser("evaluate", help="score a submission (validate, metrics, intervals -> results.json)",
                       description="Validate a submission (every problem listed, exit 2, nothing written), "
                       "then compute the metrics its protocol asks for with intervals from half-sampling of "
                       "the protocol's clusters (scenes; none below 5) and write results JSON (with each "
                       "metric's replicates) plus a .features.npz sidecar.")
    p.add_argument("submission", metavar="SUBMISSION", help="submission folder (holds submission.json)")
    p.add_argument("--data", metavar="DIR", help="dataset folder (default: from submission.json and the "
                   "protocol's default location)")
    p.add_argument("--out", metavar="FILE", help="results file (default: SUBMISSION.results.json beside "
                   "the folder, or SUBMISSION.shard-I-of-N.results.json)")
    p.add_argument("--shard", metavar="I/N", help="evaluate only sequences k with k %% N == I; write a "
                   "partial result for `skyeyes-bench merge`")
    p.add_argument("--protocol", metavar="ID@N", help="score with this protocol instead of the one submission.json "
                   "names; it must score the same data, e.g. synthtown@3 for a synthtown@2 submission (same frames, "
                   "plus the seen/unseen and warp metrics)")
    p.add_argument("--device", default="cpu", metavar="DEV",
                   help="where the feature extractors (Inception, I3D, LPIPS) run: cpu (default; the reference), "
                   "cuda or cuda:N for speed, auto (cuda when visible). GPU features agree with CPU ones to float "
                   "rounding (TF32 off), so scores may differ in the last digits; the device is recorded in the "
                   "results (extractors.<id>.device) and shards scored on different devices do not merge")
    p.add_argument("--force", action="store_true", help="replace an existing results file")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--json", action="store_true", help="print the results JSON instead of a summary")
    p.set_defaults(run=run)


def run(args) -> int:
    from ..evaluate import default_out, evaluate, format_summary, parse_shard

    shard = parse_shard(args.shard)
    out = args.out or default_out(args.submission, shard)
    res = evaluate(args.submission, data=args.data, out=out, shard=shard, force=args.force,
                   progress=not args.quiet, protocol=args.protocol, device=args.device)
    if args.json:
        print(json.dumps(res, indent=2))
    elif shard:
        print(f"shard {shard[0]}/{shard[1]}: {len(res['frames'])} frames -> {out} "
              f"(merge all {shard[1]} with `skyeyes-bench merge PARTS... --out results.json`)")
    else:
        print(format_summary(res))
        print(f"wrote {out}")
    return 0
