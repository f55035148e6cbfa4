"""`skyeyes-bench leaderboard [--check]`: regenerate (or verify) the leaderboard files."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("leaderboard", help="regenerate leaderboard/README.md, index.html and plots",
                       description="Regenerate leaderboard/README.md, leaderboard/index.html and "
                       "leaderboard/plots/*.png from leaderboard/results/*.json (measured) and "
                       "leaderboard/reported/*.toml (numbers from papers, never ranked with measured rows). "
                       "With --check, write nothing and exit 1 if the files on disk are stale.")
    p.add_argument("--root", metavar="DIR", help="leaderboard folder (default: leaderboard/ of this checkout)")
    p.add_argument("--check", action="store_true", help="exit 1 if the files differ from what the inputs generate")
    p.set_defaults(handler="skyeyes_bench.commands._leaderboard_impl:leaderboard_cmd")
