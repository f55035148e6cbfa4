"""`skyeyes-bench leaderboard [--check]`: regenerate (or verify) the leaderboard files;
`skyeyes-bench leaderboard add RESULTS.json [--name NAME] [--force]`: file a result;
`skyeyes-bench leaderboard evaluate INBOX/ [--ray [ADDRESS]]`: score, file and publish an inbox."""

from __future__ import annotations

import sys
from pathlib import Path

from ..batch import RAY_HELP, RAY_ORDER


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
    p.add_argument("--check", action="store_true", help="exit 1 if the files differ from what the inputs generate; exit 2 (one line) if a filed "
                   "result fails what `leaderboard add` checks")
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
    e = acts.add_parser("evaluate", help="score every new or changed submission folder of an inbox, file the "
                        "results and regenerate the page",
                        description="The leaderboard's intake: score every submission folder in INBOX that is new "
                        "or changed since it was filed (sha256 of its files, recorded in OUT/intake.json), in turn "
                        "or with --ray as shards on Ray; file each result as `leaderboard add --name FOLDER` does "
                        "(its results in OUT/FOLDER.results.json); then regenerate the page. A submission that "
                        "cannot be scored or filed is one line naming it, and is skipped: the others are filed, "
                        "the page is regenerated, and the exit code is 2 (1 for an internal error). docs/scale.md")
    e.add_argument("inbox", nargs="?", metavar="INBOX", help="folder of submission folders (each a plain name: the "
                   "name its result is filed under)")
    e.add_argument("--root", dest="ev_root", metavar="DIR", help="leaderboard folder (default: leaderboard/)")
    e.add_argument("--out", dest="ev_out", metavar="DIR", help="results files and the intake's record (default: "
                   "INBOX.intake/ beside the inbox)")
    e.add_argument("--data", metavar="DIR", help="dataset folder (default: from each submission.json, as `evaluate`)")
    e.add_argument("--ray", nargs="?", const="", metavar="ADDRESS", help=RAY_HELP + RAY_ORDER)
    e.add_argument("--shards", type=int, metavar="N", help="with --ray: shards per submission (default: one per task "
                   "the cluster runs at once)")
    e.add_argument("--device", default="cpu", metavar="DEV", help="where the feature extractors run, as `evaluate "
                   "--device` (default: cpu, the reference)")
    e.add_argument("--allow-missing", action="store_true", help="file results with a metric the protocol requires "
                   "reported unavailable (its weights missing here); without it such a submission is one line and "
                   "skipped, as `evaluate` without --allow-missing refuses it")
    e.add_argument("--quiet", action="store_true", help="no progress bars")
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
        from ..leaderboard.add import check_results

        # every filed result passes what `leaderboard add` checks: a row that arrives by a pull
        # request (docs/leaderboard.md, "Submitting a row") is held to the same rules
        for p in sorted((root / "results").glob("*.json")):
            check_results(p)
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


def _evaluate(args) -> int:
    from ..batch import ray_address
    from ..errors import UserError
    from ..leaderboard.intake import intake

    folders = [args.inbox] if args.inbox else []
    ray = ray_address(args.ray, folders)
    if len(folders) != 1:
        raise UserError("leaderboard evaluate: expected one INBOX folder")
    if args.shards is not None and ray is None:
        raise UserError("--shards N: only with --ray")
    if ray is not None:
        from ..ray_exec import require_ray

        require_ray()  # before any work: without Ray, one line that says how to install it
    lines, rc = intake(folders[0], root=_root(args.ev_root or args.root), out=args.ev_out, data=args.data, ray=ray,
                       shards=args.shards, device=args.device, progress=not args.quiet,
                       allow_missing=args.allow_missing)
    for line in lines:
        print(line, file=sys.stderr if ": error: " in line else sys.stdout)
    return rc


#: The group's actions (without one, `leaderboard` regenerates the page).
ACTIONS = {"add": _add, "evaluate": _evaluate}
