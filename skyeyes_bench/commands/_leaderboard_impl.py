from __future__ import annotations

import sys
from pathlib import Path

from .. import leaderboard, paths
from ..errors import UserError


def _root(args) -> Path:
    if args.root:
        return Path(args.root)
    repo = paths.repo_root()
    if repo is None:
        raise UserError("not in a source checkout: pass --root DIR (the leaderboard folder)")
    return repo / "leaderboard"


def leaderboard_cmd(args) -> int:
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
