"""`skyeyes-bench data synthtown` and `skyeyes-bench data gallery` (argparse only at import)."""

from __future__ import annotations

_PRESETS = ("smoke", "small", "paper")


def register(ds) -> None:
    q = ds.add_parser(
        "synthtown", help="generate the built-in SynthTown dataset (protocol synthtown@1)",
        description="Render SynthTown, the procedural aerial/ground dataset, in the canonical layout: "
        "train towns train-0, train-1 and the held-out test town test-0; per lane 8 ground sequences "
        "(yaw offsets k*45 deg, every 2 m, 2 m high, pitch 0) and aerial views at 52 m, pitch -45 deg; "
        "RGB, depth (EXR, metres) and semantics. Presets: smoke (tests, seconds), small (the protocol's "
        "official 128x128, minutes on a CPU), paper (512x512, hours on a CPU).")
    q.add_argument("--out", metavar="DIR", help="dataset folder to create (default: the data cache, "
                   "<cache>/data/synthtown-<preset>[-seed<N>], where evaluate and reproduce look)")
    q.add_argument("--preset", choices=_PRESETS, default="small", help="size preset (default: small)")
    q.add_argument("--seed", type=int, default=0, help="dataset seed: other towns and lanes (default: 0)")
    q.add_argument("--force", action="store_true", help="replace an existing dataset folder")
    q.add_argument("--workers", type=int, default=None, help="render processes (default: 1 for smoke, else 2)")
    q.add_argument("--quiet", action="store_true", help="no progress bar")
    q.set_defaults(handler="skyeyes_bench.data.synthtown.cli_impl:synthtown_cmd")

    g = ds.add_parser(
        "gallery", help="write a gallery PNG: aerial/ground pairs with depth and semantics",
        description="Compose one PNG with, per row, an aerial view and a ground view of the same lane, "
        "each with its depth and semantic labels. From a dataset folder (--dataset), or rendered on the "
        "fly from SynthTown (--preset/--seed, nothing else is written).")
    g.add_argument("--out", metavar="PNG", required=True, help="image to write")
    g.add_argument("--dataset", metavar="DIR", help="a dataset in the canonical layout with depth and semantics")
    g.add_argument("--preset", choices=_PRESETS, default="small", help="SynthTown preset to render from")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--rows", type=int, default=3, help="lanes shown (default: 3)")
    g.add_argument("--size", type=int, default=160, help="tile size in pixels when rendering (default: 160)")
    g.set_defaults(handler="skyeyes_bench.data.synthtown.cli_impl:gallery_cmd")
