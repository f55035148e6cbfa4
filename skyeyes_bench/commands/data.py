"""`skyeyes-bench data ...`: check datasets, generate SynthTown, import CARLA / MatrixCity."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("data", help="check, generate and import datasets (canonical layout)",
                       description="Datasets in the canonical layout of DESIGN.md.")
    p.set_defaults(group_parser=p)
    ds = p.add_subparsers(title="actions", metavar="ACTION")

    q = ds.add_parser("check", help="validate a dataset folder and print a summary",
                      description="Validate a dataset (files, poses, intrinsics, sequences, splits); "
                      "print every problem, or a summary of scenes, sequences and frames per split.")
    q.add_argument("root", metavar="DIR", help="dataset folder (holds dataset.json)")
    q.add_argument("--json", action="store_true", help="print the summary as JSON")
    q.add_argument("--quick", action="store_true",
                   help="read image headers only (default: decode every image, finding truncated files)")
    q.set_defaults(handler="skyeyes_bench.commands._data_impl:check_cmd")

    # Further actions register themselves from their own modules (kept apart so that each
    # capability is one file): synthtown, gallery, import-carla, import-matrixcity.
    import importlib

    for mod in ("skyeyes_bench.data.synthtown.cli", "skyeyes_bench.data.importers_cli"):
        try:
            m = importlib.import_module(mod)
        except ModuleNotFoundError as e:
            if e.name is not None and mod.startswith(e.name):
                continue
            raise
        m.register(ds)
