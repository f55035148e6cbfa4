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
    p.set_defaults(run=run)


def run(args) -> int:
    from pathlib import Path

    from .. import fileio
    from ..errors import UserError
    from ..evaluate import FEATURES_OUTPUT, RESULTS_OUTPUT, features_path, format_summary, merge

    out = Path(args.out)
    if not out.name:  # '.', '/': no file name to put the sidecar beside
        raise UserError(f"{out}: is a folder; expected the path of an output file")
    # Before any work: neither the results nor their sidecar may be a part or a part's sidecar
    # (`--out p0` would write p0.features.npz, the sidecar of part p0.json), and --force replaces
    # only earlier results (`fileio.check_output`).
    parts = [Path(p) for p in args.parts]
    inputs = [*parts, *(features_path(p) for p in parts if p.name)]
    fileio.check_output(out, force=args.force, sidecars=[features_path(out)], inputs=inputs,
                        inputs_are="the parts being merged (or their sidecars)", kind=RESULTS_OUTPUT,
                        sidecar_kind=FEATURES_OUTPUT)
    with fileio.reading(*inputs):  # checked again as the files are renamed in
        res = merge(args.parts, out=args.out, force=args.force, progress=not args.quiet)
    print(format_summary(res))
    print(f"wrote {args.out}")
    return 0
