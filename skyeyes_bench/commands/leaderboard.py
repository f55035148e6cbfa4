"""`skyeyes-bench leaderboard [--check]`: regenerate (or verify) the leaderboard files."""

from __future__ import annotations

import sys
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("leaderboard", help="regenerate leaderboard/README.md, index.html and plots",
                       description="Regenerate leaderboard/README.md, leaderboard/index.html and "
                       "leaderboard/plots/*.png from leaderboard/results/*.json (measured) and "
                       "leaderboard/reported/*.toml (numbers from papers, never ranked with measured rows). "
                       "With --check, write nothing and exit 1 if the files on disk are stale.")
    p.add_argument("--root", metavar="DIR", help="leaderboard folder (default: leaderboard/ of this checkout)")
    p.add_argument("--check", action="store_true", help="exit 1 if the files differ from what the inputs generate")
    p.set_defaults(run=run)


def _root(args) -> Path:
    from .. import paths
    from ..errors import UserError

    if args.root:
        return Path(args.root)
    repo = paths.repo_root()
    if repo is None:
        raise UserError("not in a source checkout: pass --root DIR (the leaderboard folder)")
    return repo / "leaderboard"


def run(args) -> int:
    from .. import leaderboard

    root = _root(args)
    if args.check:
        stale = leaderboard.check(root)
        if stale:
            print(f"{root}: leaderboard is stale; run `skyeyes-bench leaderboard` and commit:", file=sys.stderr)
            for s in stale:
                print(f"  {s}", file=sys.stderr)
            return 1
        print(f"{root}: leaderboard up to date")
        return 0
    files = leaderboard.write(root)
    print(f"{root}: wrote {', '.join(files)}")
    return 0
