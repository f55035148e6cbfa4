"""`skyeyes-bench leaderboard [--check]`: regenerate (or verify) the leaderboard files;
`skyeyes-bench leaderboard add RESULTS.json [--name NAME] [--force]`: file a result."""

from __future__ import annotations

import sys
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("leaderboard", help="regenerate leaderboard/README.md, index.html, plots, strips and "
                       "sequence animations; `leaderboard add` files a result",
                       description="Regenerate leaderboard/README.md, leaderboard/index.html, "
                       "leaderboard/plots/*.png, leaderboard/strips/*.png and the test sequence's animation "
                       "leaderboard/strips/*-sequence.webp from leaderboard/results/*.json (measured), "
                       "leaderboard/frames/ (strip frames, sequences) and leaderboard/reported/*.toml (numbers "
                       "from papers, never ranked with measured rows). With --check, write nothing and exit 1 "
                       "if the files on disk are stale. `leaderboard add RESULTS.json` files a result first.")
    p.add_argument("--root", metavar="DIR", help="leaderboard folder (default: leaderboard/ of this checkout)")
    p.add_argument("--check", action="store_true", help="exit 1 if the files differ from what the inputs generate")
    # dest is not "action": the CLI treats a group whose "action" is None as "print its help"
    acts = p.add_subparsers(dest="lb_action", metavar="ACTION", parser_class=type(p))
    a = acts.add_parser("add", help="check a results file and file it as leaderboard/results/<name>.json",
                        description="Check RESULTS.json (complete results of a known protocol with the "
                        "submission's run time) and file it as <root>/results/<name>.json; save the strip frames "
                        "and one fixed test sequence as an animated WebP (of the submission and, once per protocol "
                        "and dataset, of the ground truth) into <root>/frames/<protocol>_<dataset digest>/ when "
                        "they are on this machine. "
                        "Then run `skyeyes-bench leaderboard` to regenerate the page.")
    a.add_argument("results", metavar="RESULTS.json", help="a results file written by `evaluate` or `merge`")
    a.add_argument("--name", help="name to file it under (default: the submission's method name)")
    a.add_argument("--root", dest="add_root", metavar="DIR", help="leaderboard folder (default: leaderboard/)")
    a.add_argument("--force", action="store_true", help="replace a result already filed under that name")
    p.set_defaults(run=run)


def _root(arg) -> Path:
    from .. import paths
    from ..errors import UserError

    if arg:
        return Path(arg)
    repo = paths.repo_root()
    if repo is None:
        raise UserError("not in a source checkout: pass --root DIR (the leaderboard folder)")
    return repo / "leaderboard"


def run(args) -> int:
    action = getattr(args, "lb_action", None)
    if action is not None:
        return ACTIONS[action](args)
    from .. import leaderboard

    root = _root(args.root)
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


def _add(args) -> int:
    from .. import leaderboard

    root = _root(args.add_root or args.root)
    for line in leaderboard.add_result(args.results, root=root, name=args.name, force=args.force):
        print(line)
    print("run `skyeyes-bench leaderboard` to regenerate the page")
    return 0


#: The group's actions (without one, `leaderboard` regenerates the page).
ACTIONS = {"add": _add}
