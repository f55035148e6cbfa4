"""`skyeyes-bench seeds DIR`: one results file of several seeds from their separate runs."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("seeds", help="combine the results of several seeds run apart into one with their spread",
                       description="Write DIR/results.json from DIR/seed-<s>/results.json (two or more: one method's "
                       "runs with different seeds, each scored by `evaluate --out DIR/seed-<s>/results.json`): the "
                       "lowest seed's results with a 'seeds' block of every seed's values and their spread, the file "
                       "`reproduce --seeds N` writes. For seeds run on other machines, Slurm array tasks or a GPU "
                       "(docs/reproduce.md, 'Several seeds'); `compare` tests two such files against the seed "
                       "spread and `leaderboard add` shows it.")
    p.add_argument("dir", metavar="DIR", help="folder of seed-<s>/results.json")
    p.add_argument("--force", action="store_true", help="replace a results.json there that is not of several seeds")
    p.add_argument("--json", action="store_true", help="print the seeds block as JSON instead of a summary")
    p.set_defaults(run=run)


def run(args) -> int:
    from pathlib import Path

    from ..seeds import assemble, format_spread

    doc = assemble(Path(args.dir), force=args.force)
    if args.json:
        import json

        print(json.dumps(doc["seeds"], indent=2))
        return 0
    print(format_spread(doc["seeds"], (doc.get("submission") or {}).get("method")))
    print(f"wrote {Path(args.dir) / 'results.json'}")
    return 0
