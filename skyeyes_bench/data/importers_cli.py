"""`skyeyes-bench data import-carla|import-matrixcity` (argparse only; the work is in `importers`)."""

from __future__ import annotations


def _common(q, default_protocol: str) -> None:
    q.add_argument("src", metavar="SRC", help="source capture folder")
    q.add_argument("out", metavar="OUT", help="output dataset folder (canonical layout); must not exist")
    q.add_argument("--protocol", default=default_protocol, metavar="ID[@N]",
                   help=f"protocol the dataset is for; its train/test towns give the splits (default: {default_protocol})")
    q.add_argument("--split", choices=("train", "test"),
                   help="split for towns the protocol does not list (default: refuse them)")
    q.add_argument("--force", action="store_true", help="replace OUT if it exists (only once the new one is complete)")
    q.add_argument("--no-progress", action="store_true", help="no progress bar")


def register(ds) -> None:
    q = ds.add_parser("import-carla", help="convert a CARLA capture folder into the canonical layout",
                      description="Convert a CARLA capture folder (RGB PNGs, depth-camera PNGs, capture.json with "
                      "sensor transforms; see docs/formats.md) into the canonical layout. Poses go to the "
                      "right-handed world (CARLA y negated); depth is decoded to float32 EXR metres.")
    _common(q, "carla-town04")
    q.set_defaults(handler="skyeyes_bench.data.importers:import_carla_cmd")

    q = ds.add_parser("import-matrixcity", help="convert MatrixCity / CitySample captures into the canonical layout",
                      description="Convert MatrixCity / CitySample captures (aerial and street blocks; raw "
                      "transforms.json or paper-split transforms_*.json; EXR depth in cm) into the canonical "
                      "layout. Street tracks are cut into lanes, each horizontal cube-map face direction "
                      "becomes a sequence, resampled to the protocol's step where possible; what differs "
                      "from the protocol is recorded in dataset.json 'meta'. See docs/formats.md.")
    _common(q, "citysample-region5")
    q.add_argument("--town", default="matrixcity",
                   help="town / region name of the scenes, '<town>-laneNN' (default: matrixcity)")
    q.add_argument("--pose-format", default="auto", choices=("auto", "raw", "paper"),
                   help="raw transforms.json (rotation x0.01, metres) or paper-split transforms_*.json "
                   "(100 m units); auto: raw if present")
    q.add_argument("--convention", default="opengl", choices=("opengl", "opencv"),
                   help="camera axes of the stored poses (MatrixCity: opengl)")
    q.add_argument("--depth-root", metavar="DIR",
                   help="folder mirroring SRC with the depth EXRs (default: beside the images, or '<folder>_depth/')")
    q.add_argument("--aerial-radius", type=float, default=60.0, metavar="M",
                   help="attach aerial frames whose view centre on the ground lies within M metres of a lane point")
    q.set_defaults(handler="skyeyes_bench.data.importers:import_matrixcity_cmd")
