from __future__ import annotations

import json

from ..evaluate import default_out, evaluate, format_summary, parse_shard


def evaluate_cmd(args) -> int:
    shard = parse_shard(args.shard)
    out = args.out or default_out(args.submission, shard)
    res = evaluate(args.submission, data=args.data, out=out, shard=shard, force=args.force,
                   progress=not args.quiet)
    if args.json:
        print(json.dumps(res, indent=2))
    elif shard:
        print(f"shard {shard[0]}/{shard[1]}: {len(res['frames'])} frames -> {out} "
              f"(merge all {shard[1]} with `skyeyes-bench merge PARTS... --out results.json`)")
    else:
        print(format_summary(res))
        print(f"wrote {out}")
    return 0
