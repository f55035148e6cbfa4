"""`skyeyes-bench merge PARTS... --out results.json`: combine sharded evaluations."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("merge", help="merge the partial results of `evaluate --shard I/N`",
                       description="Merge the N partial results of `skyeyes-bench evaluate --shard I/N` "
                       "(per-frame values and features) into results equal to an unsharded run.")
    p.add_argument("parts", nargs="+", metavar="PART", help="partial results JSON files (all N shards)")
    p.add_argument("--out", required=True, metavar="FILE", help="results file to write")
    p.add_argument("--force", action="store_true", help="replace an existing results file")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--json", action="store_true", help="print the results JSON instead of a summary")
    p.set_defaults(run=run)


def run(args) -> int:
    from ..evaluate import format_summary, merge

    # The output discipline (no part or part's sidecar overwritten, --force for earlier results
    # only, a lock against a second merge) is `shards.merge`'s.
    res = merge(args.parts, out=args.out, force=args.force, progress=not args.quiet)
    if args.json:
        import json

        print(json.dumps(res, indent=2))
        return 0
    print(format_summary(res))
    print(f"wrote {args.out}")
    return 0
