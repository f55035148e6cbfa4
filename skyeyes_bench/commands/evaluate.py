"""`skyeyes-bench evaluate SUBMISSION`: score a submission against its protocol."""

from __future__ import annotations

import json
import sys

from ..batch import RAY_HELP, RAY_ORDER


def register(sub) -> None:
    p = sub.add_parser("evaluate", help="score a submission (validate, metrics, intervals -> results.json)",
                       description="Validate a submission (every problem listed, exit 2, nothing written), "
                       "then compute the metrics its protocol asks for with intervals from half-sampling of "
                       "the protocol's clusters (scenes; none below 5) and write results JSON (with each "
                       "metric's replicates) plus a .features.npz sidecar. A metric the protocol requires that "
                       "cannot be computed here (missing weights: `skyeyes-bench weights fetch`; a dataset "
                       "without depth) is exit 2 with one line naming it, before any scoring where that is "
                       "known up front, unless --allow-missing.")
    p.add_argument("submissions", nargs="*", metavar="SUBMISSION",
                   help="submission folder (holds submission.json); several are scored one after another (or "
                   "together with --ray), each into SUBMISSION.results.json, and one that fails is reported in one "
                   "line and skipped (exit 2 after the others)")
    p.add_argument("--data", metavar="DIR", help="dataset folder (default: from submission.json and the "
                   "protocol's default location)")
    p.add_argument("--out", metavar="FILE", help="results file (default: SUBMISSION.results.json beside "
                   "the folder, or SUBMISSION.shard-I-of-N.results.json)")
    p.add_argument("--shard", metavar="I/N", help="evaluate only sequences k with k %% N == I; write a "
                   "partial result for `skyeyes-bench merge`")
    p.add_argument("--ray", nargs="?", const="", metavar="ADDRESS",
                   help=RAY_HELP + RAY_ORDER + ". Each submission is split into shards (sequence groups) that run as "
                   "Ray tasks and are merged as `merge` does: the numbers of one process")
    p.add_argument("--shards", type=int, metavar="N", help="with --ray: shards per submission (default: one per task "
                   "the cluster runs at once, at most one per test sequence); the numbers never depend on it")
    p.add_argument("--protocol", metavar="ID@N", help="score with this protocol instead of the one submission.json "
                   "names; it must score the same data, e.g. synthtown@3 for a synthtown@2 submission (same frames, "
                   "plus the seen/unseen and warp metrics)")
    p.add_argument("--split", choices=("test", "val"),
                   help="the split the submission must hold (default: the one its submission.json names): test, "
                   "the protocol's ranked split, or val, the validation split settings are chosen on (a "
                   "submission made with `reproduce --split val`; its results say so and are never filed)")
    p.add_argument("--device", default="cpu", metavar="DEV",
                   help="where the feature extractors (Inception, I3D, LPIPS) run: cpu (default; the reference), "
                   "cuda or cuda:N for speed, auto (cuda when visible). GPU features agree with CPU ones to float "
                   "rounding (TF32 off), so scores may differ in the last digits; the device is recorded in the "
                   "results (extractors.<id>.device) and shards scored on different devices do not merge. With "
                   "--ray: auto gives each shard task a GPU where the cluster has any (else the CPU); cuda needs one")
    p.add_argument("--allow-missing", action="store_true",
                   help="partial scores: write the results with the metrics that cannot be computed here marked "
                   "\"unavailable\" (with the reason and the fix) and exit 0 (default: exit 2 naming them)")
    p.add_argument("--force", action="store_true", help="replace an existing results file")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--json", action="store_true", help="print the results JSON instead of a summary (with "
                   "--shard: the partial results)")
    p.set_defaults(run=run)


def run(args) -> int:
    from ..batch import ray_address
    from ..errors import UserError

    subs = list(args.submissions)
    ray = ray_address(args.ray, subs)
    if not subs:
        raise UserError("evaluate: expected at least one SUBMISSION folder")
    if args.shards is not None and ray is None:
        raise UserError("--shards N: only with --ray (for one machine's shards use --shard I/N and `merge`)")
    if len(subs) > 1 or ray is not None:
        return _many(args, subs, ray)
    return _one(args, subs[0])


def _one(args, sub: str) -> int:
    from ..evaluate import default_out, evaluate, format_summary, parse_shard

    shard = parse_shard(args.shard)
    out = args.out or default_out(sub, shard)
    res = evaluate(sub, data=args.data, out=out, shard=shard, force=args.force,
                   progress=not args.quiet, protocol=args.protocol, device=args.device, split=args.split,
                   allow_missing=args.allow_missing)
    if args.json:
        print(json.dumps(res, indent=2))
    elif shard:
        print(f"shard {shard[0]}/{shard[1]}: {len(res['frames'])} frames -> {out} "
              f"(merge all {shard[1]} with `skyeyes-bench merge PARTS... --out results.json`)")
    else:
        print(format_summary(res))
        print(f"wrote {out}")
    return 0


def _many(args, subs: list[str], ray: str | None) -> int:
    """Several submissions, or any on Ray: each scored (in turn, or as shards on Ray) into its
    own results file; one that fails is one line on stderr and the exit code says so."""
    from pathlib import Path

    from ..batch import Job, evaluate_batch, exit_code
    from ..errors import UserError
    from ..evaluate import default_out, format_summary

    if args.shard is not None:
        raise UserError("--shard I/N: one SUBMISSION without --ray (--ray splits each submission itself; "
                        "--shards N says into how many)")
    for flag, given in (("--out", args.out), ("--json", args.json), ("--split", args.split)):
        if given and len(subs) > 1:
            raise UserError(f"{flag}: only with one SUBMISSION (several write SUBMISSION.results.json each)")
    jobs = [Job(Path(s), Path(args.out) if args.out else default_out(s), data=args.data, protocol=args.protocol)
            for s in subs]
    outcomes = evaluate_batch(jobs, ray=ray, shards=args.shards, device=args.device, force=args.force,
                              progress=not args.quiet, allow_missing=args.allow_missing)
    for o in outcomes:
        if o.error is not None:
            print(f"skyeyes-bench: error: {o.job.sub}: {o.error}", file=sys.stderr)
        elif args.json:
            print(json.dumps(o.results, indent=2))
        else:
            print(format_summary(o.results))
            print(f"wrote {o.job.out}")
    return exit_code(outcomes)
