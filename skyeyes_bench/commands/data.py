"""`skyeyes-bench data check|synthtown|gallery|capture-carla|import-carla|import-matrixcity`: check
datasets, generate SynthTown, capture CARLA towns, import CARLA / MatrixCity captures (all in the
canonical layout)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

#: SynthTown size presets (`skyeyes_bench.data.synthtown.presets.PRESETS`, not imported here so
#: that building the parser stays light).
_PRESETS = ("smoke", "small", "small-v1", "small-stiff", "paper")


def register(sub) -> None:
    p = sub.add_parser("data", help="check, generate and import datasets (canonical layout)",
                       description="Datasets in the canonical layout of docs/formats.md.")
    p.set_defaults(run=run, group_parser=p)
    ds = p.add_subparsers(title="actions", dest="action", metavar="ACTION")
    _add_check(ds)
    _add_synthtown(ds)
    _add_gallery(ds)
    _add_capture_carla(ds)
    _add_import_carla(ds)
    _add_import_matrixcity(ds)


def _add_check(ds) -> None:
    """`data check DIR`: validate a dataset."""
    q = ds.add_parser("check", help="validate a dataset folder and print a summary",
                      description="Validate a dataset (files, poses, intrinsics, sequences, splits); "
                      "print every problem, or a summary of scenes, sequences and frames per split.")
    q.add_argument("root", metavar="DIR", help="dataset folder (holds dataset.json)")
    q.add_argument("--json", action="store_true", help="print the summary as JSON")
    q.add_argument("--quick", action="store_true",
                   help="read image headers only (default: decode every image, finding truncated files)")


def _add_synthtown(ds) -> None:
    """`data synthtown`: generate SynthTown."""
    q = ds.add_parser(
        "synthtown", help="generate the built-in SynthTown dataset (protocol synthtown@2; small-v1: @1)",
        description="Render SynthTown, the procedural aerial/ground dataset, in the canonical layout: "
        "train towns train-0, train-1 and the held-out test town test-0; per lane 8 ground sequences "
        "(yaw offsets k*45 deg, every 2 m, 2 m high, pitch 0) and aerial views at 52 m, pitch -45 deg; "
        "RGB, depth (EXR, metres) and semantics. Presets: smoke (tests, seconds; synthtown@1), small "
        "(synthtown@2's official data: 128x128, 8 test lanes, 32-frame sequences; ~20 min on 2 cores), "
        "small-v1 (synthtown@1's official data), small-stiff (synthtown-stiff@1: small's train towns and a "
        "tilted, cloudy test town), paper (512x512, hours on a CPU). --split val makes the preset's "
        "validation data instead: the same train towns and the validation town val-0, in a dataset of its "
        "own (<dataset>-val), where settings are chosen; it is never ranked.")
    q.add_argument("--out", metavar="DIR", help="dataset folder to create (default: the data cache, "
                   "<cache>/data/<dataset>[-seed<N>], e.g. synthtown-v2-small, where evaluate and reproduce look)")
    q.add_argument("--preset", choices=_PRESETS, default="small", help="size preset (default: small)")
    q.add_argument("--seed", type=int, default=0, help="dataset seed: other towns and lanes (default: 0)")
    q.add_argument("--split", choices=("test", "val"), default="test",
                   help="test: the protocol's train and test towns (default); val: the train towns and the "
                   "validation towns, the data to choose a method's settings on")
    q.add_argument("--force", action="store_true", help="replace an existing dataset folder")
    q.add_argument("--workers", type=int, default=None, help="render processes (default: 1 for smoke, else 2)")
    q.add_argument("--quiet", action="store_true", help="no progress bar")


def _add_gallery(ds) -> None:
    """`data gallery`: a PNG of aerial/ground pairs."""
    q = ds.add_parser(
        "gallery", help="write a gallery PNG: aerial/ground pairs with depth and semantics",
        description="Compose one PNG with, per row, an aerial view and a ground view of the same lane, "
        "each with its depth and semantic labels. From a dataset folder (--dataset), or rendered on the "
        "fly from SynthTown (--preset/--seed, nothing else is written).")
    q.add_argument("--out", metavar="PNG", required=True, help="image to write")
    q.add_argument("--dataset", metavar="DIR", help="a dataset in the canonical layout with depth and semantics")
    q.add_argument("--preset", choices=_PRESETS, default="small", help="SynthTown preset to render from")
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--rows", type=int, default=3, help="lanes shown (default: 3)")
    q.add_argument("--size", type=int, default=160, help="tile size in pixels when rendering (default: 160)")


def _add_capture_carla(ds) -> None:
    """`data capture-carla`: capture (or plan) a CARLA town."""
    q = ds.add_parser(
        "capture-carla", help="capture a CARLA town on a running server into a capture folder (or plan it)",
        description="Capture the protocol's lanes of a CARLA town (carla-town04@1: ground cameras every 2 m at "
        "2 m height, pitch 0, yaws k*45 deg; aerial cameras at 52 m, pitch -45 deg; 512x512, fov 90) with RGB "
        "and depth sensors in synchronous mode, into OUT/<town>/laneNN/{rgb,depth}/ and OUT/capture.json, which "
        "'data import-carla OUT DATASET' reads. Lanes come from the map's waypoints: driving lanes outside "
        "junctions, one per road, resampled every 2 m from the lane's first waypoint, --min-points..--max-points "
        "long (docs/formats.md, 'CARLA capture'). OUT/plan.json holds every planned transform; --plan-only stops "
        "there. A time-out is retried; running the command again resumes (finished frames are kept). Needs "
        "the 'carla' client package (pip install 'skyeyes-bench[carla]', matching the server's version), "
        "except for --plan-only --waypoints FILE.")
    q.add_argument("--town", required=True, help="CARLA map, e.g. Town04 (loaded on the server if another is)")
    q.add_argument("--out", metavar="DIR", required=True, help="capture folder (created; reused to resume)")
    q.add_argument("--host", default="localhost", help="CARLA server host (default: localhost)")
    q.add_argument("--port", type=int, default=2000, help="CARLA server RPC port (default: 2000)")
    q.add_argument("--protocol", default="carla-town04", metavar="ID[@N]",
                   help="protocol whose [capture] geometry and image size to use (default: carla-town04)")
    q.add_argument("--plan-only", action="store_true",
                   help="write OUT/plan.json (every transform, in capture.json's format) and stop")
    src = q.add_mutually_exclusive_group()
    src.add_argument("--waypoints", metavar="FILE", help="the map's waypoints as JSON (format in docs/formats.md; "
                     "a server run writes OUT/waypoints.json): plan without a server and without the carla package")
    src.add_argument("--xodr", metavar="FILE", help="the town's OpenDRIVE file (CARLA ships <town>.xodr): "
                     "waypoints without a server, through the carla package")
    q.add_argument("--waypoint-distance", type=float, default=1.0, metavar="M",
                   help="spacing of the map's waypoints before resampling to the 2 m step (default: 1.0)")
    q.add_argument("--min-points", type=int, default=16,
                   help="shortest lane kept, in points (default: 16, one 16-frame FVD clip)")
    q.add_argument("--max-points", type=int, default=32, help="points per lane, from its start (default: 32)")
    q.add_argument("--max-lanes", type=int, help="at most this many lanes, evenly spaced in road order (default: all)")
    q.add_argument("--aerial-stride", type=int, default=4, help="aerial cameras every N-th lane point (default: 4)")
    q.add_argument("--aerial-yaws", type=int, default=8, help="aerial headings per aerial point (default: 8)")
    q.add_argument("--timeout", type=float, default=20.0, metavar="S",
                   help="seconds to wait for the server and for each sensor image (default: 20)")
    q.add_argument("--retries", type=int, default=3, help="extra attempts per frame after a time-out (default: 3)")
    q.add_argument("--force", action="store_true", help="start over when OUT holds a capture of another plan")
    q.add_argument("--no-progress", action="store_true", help="no progress bar")


def _add_import_carla(ds) -> None:
    """`data import-carla SRC OUT`: a CARLA capture folder."""
    q = ds.add_parser("import-carla", help="convert a CARLA capture folder into the canonical layout",
                      description="Convert a CARLA capture folder (RGB PNGs, depth-camera PNGs, capture.json with "
                      "sensor transforms; see docs/formats.md) into the canonical layout. Poses go to the "
                      "right-handed world (CARLA y negated); depth is decoded to float32 EXR metres.")
    _import_arguments(q, "carla-town04")


def _add_import_matrixcity(ds) -> None:
    """`data import-matrixcity SRC OUT`: MatrixCity / CitySample captures."""
    q = ds.add_parser("import-matrixcity", help="convert MatrixCity / CitySample captures into the canonical layout",
                      description="Convert MatrixCity / CitySample captures (aerial and street blocks; raw "
                      "transforms.json or paper-split transforms_*.json; EXR depth in cm) into the canonical "
                      "layout. Street tracks are cut into lanes, each horizontal cube-map face direction "
                      "becomes a sequence, resampled to the protocol's step where possible; what differs "
                      "from the protocol is recorded in dataset.json 'meta'. See docs/formats.md.")
    _import_arguments(q, "citysample-region5")
    q.add_argument("--town", default="matrixcity",
                   help="town / region name of the scenes, '<town>-laneNN' (default: matrixcity); the protocol's "
                   "train/test towns give the split")
    q.add_argument("--region", action="append", metavar="TOWN=BLOCK[,BLOCK...]", default=[],
                   help="instead of --town: scenes of the lanes that these aerial blocks (MatrixCity folder names, "
                   "e.g. region5=block_10, or paper blocks, e.g. region5=block_E) see best are named TOWN-laneNN; "
                   "repeat for each region, so one import holds train and test regions; lanes no region covers "
                   "are left out (docs/formats.md: the public stand-in for region 5)")
    q.add_argument("--pose-format", default="auto", choices=("auto", "raw", "paper"),
                   help="raw transforms.json (rotation x0.01, metres) or paper-split transforms_*.json "
                   "(100 m units); auto: raw if present")
    q.add_argument("--convention", default="opengl", choices=("opengl", "opencv"),
                   help="camera axes of the stored poses (MatrixCity: opengl)")
    q.add_argument("--depth-root", metavar="DIR", action="append",
                   help="folder mirroring SRC with the depth EXRs, '<block>_depth/NNNN.exr' as MatrixCity ships them; "
                   "repeat to search several, first match wins (default: SRC's siblings '<SRC>_depth_float32' and "
                   "'<SRC>_depth' when they exist; always also beside the images and in '<block>_depth/')")
    q.add_argument("--include", action="append", metavar="GLOB",
                   help="only pose files whose path under SRC matches GLOB (repeatable), e.g. "
                   "'aerial/train/*/transforms.json' and 'street/train_dense/*/transforms.json' to take one set "
                   "of a full download (default: every pose file of the chosen --pose-format)")
    q.add_argument("--aerial-radius", type=float, default=60.0, metavar="M",
                   help="attach aerial frames whose view centre on the ground lies within M metres of a lane point")


def _import_arguments(q, default_protocol: str) -> None:
    """The arguments both importers take."""
    q.add_argument("src", metavar="SRC", help="source capture folder")
    q.add_argument("out", metavar="OUT", help="output dataset folder (canonical layout); must not exist")
    q.add_argument("--protocol", default=default_protocol, metavar="ID[@N]",
                   help=f"protocol the dataset is for; its train/test towns give the splits (default: {default_protocol}, "
                   "the latest version; dataset.json names the version whose data it is, e.g. @1 for @2, which "
                   "scores @1's frames with the depth metrics too)")
    q.add_argument("--split", choices=("train", "test"),
                   help="split for towns the protocol does not list (default: refuse them)")
    q.add_argument("--force", action="store_true", help="replace OUT if it exists (only once the new one is complete)")
    q.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args) -> int:
    return ACTIONS[args.action](args)


def _check(args) -> int:
    from ..data.layout import open_dataset
    from ..splits import check_scorable

    ds = open_dataset(args.root, check_pixels=not args.quick, progress=not args.quick and sys.stderr.isatty())
    check_scorable(ds)  # the split evaluate scores: what it refuses for, refused here
    s = ds.summary()
    if args.json:
        print(json.dumps(s, indent=2))
        return 0
    print(f"dataset {s['name']!r}  protocol {s['protocol']}  ({s['root']})")
    for split, c in s["splits"].items():
        print(f"  {split:<6} {c['scenes']:>4} scenes {c['sequences']:>5} sequences "
              f"{c['ground_frames']:>7} ground frames {c['aerial_frames']:>6} aerial frames")
    print("  resolution: " + ", ".join(f"{k} {v}" for k, v in s["resolution"].items()))
    if s["sequence_length"]:
        print(f"  sequence length: {s['sequence_length']['min']}..{s['sequence_length']['max']} frames")
    layers = [k for k, v in s["layers"].items() if v]
    print("  optional layers: " + (", ".join(layers) if layers else "none"))
    print("OK")
    return 0


def _synthtown(args) -> int:
    from .. import paths
    from ..data.importers.common import check_out
    from ..data.synthtown.generate import dataset_name, ensure_dataset, generate_dataset
    from ..errors import UserError

    if args.seed < 0:
        raise UserError(f"--seed {args.seed}: expected an integer >= 0")
    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers {args.workers}: expected an integer >= 1")
    if args.out is None and not args.force and args.workers is None:
        root = paths.data_dir() / dataset_name(args.preset, args.seed, args.split)
        existed = (root / "dataset.json").is_file()
        root = ensure_dataset(args.preset, args.seed, progress=not args.quiet, split=args.split)
        print(f"{'exists' if existed else 'wrote'} {root}")
        return 0
    out = Path(args.out) if args.out else paths.data_dir() / dataset_name(args.preset, args.seed, args.split)
    check_out(out, args.force, [])  # --force replaces a dataset (or an empty folder) only, never e.g. a home folder
    generate_dataset(out, args.preset, args.seed, overwrite=args.force, progress=not args.quiet, workers=args.workers,
                     split=args.split)
    print(f"wrote {out}")
    return 0


def _gallery(args) -> int:
    from .. import outputfiles
    from ..data.synthtown.gallery import tiles_from_dataset, tiles_rendered, write_gallery
    from ..errors import UserError

    if args.rows < 1 or args.size < 16:
        raise UserError("gallery: --rows must be >= 1 and --size >= 16")
    # the image is replaced if it exists (no --force here), but never inside the dataset it shows
    outputfiles.check_output(args.out, force=True, inputs=[args.dataset] if args.dataset else [], inputs_are="the dataset")
    if args.dataset:
        tiles = tiles_from_dataset(Path(args.dataset), args.rows)
    else:
        tiles = tiles_rendered(args.preset, args.seed, args.rows, args.size)
    out = write_gallery(tiles, Path(args.out))
    print(f"wrote {out}")
    return 0


def _capture_carla(args) -> int:
    import shutil

    from .. import inputfiles, outputfiles
    from ..data.capture import carla_live
    from ..data.capture.carla_plan import PLAN_FILE, WAYPOINTS_FILE, PlanConfig, plan_capture, read_waypoints
    from ..data.capture.carla_plan import waypoints_document
    from ..errors import UserError
    from ..protocol import load_protocol

    out = Path(args.out)
    if args.port <= 0 or args.timeout <= 0 or args.retries < 0 or args.waypoint_distance <= 0:
        raise UserError("--port and --timeout must be > 0, --retries >= 0, --waypoint-distance > 0")
    proto = load_protocol(args.protocol)
    cfg = PlanConfig.from_protocol(proto, min_points=args.min_points, max_points=args.max_points,
                                   max_lanes=args.max_lanes, aerial_stride=args.aerial_stride,
                                   aerial_yaws=args.aerial_yaws)
    server = carla_live.Server(args.host, args.port, args.timeout, args.retries)
    # 1. The map's waypoints: a file, an OpenDRIVE map, or the server.
    if args.waypoints:
        town, waypoints = read_waypoints(args.waypoints)
        if town != args.town:
            raise UserError(f"{args.waypoints}: field 'town' is {town!r}, expected {args.town!r} (--town)")
    elif args.xodr:
        waypoints = carla_live.waypoints_from_xodr(Path(args.xodr), args.town, args.waypoint_distance)
    else:
        _, client = carla_live.connect(server)
        waypoints = carla_live.waypoints_from_map(carla_live.town_world(client, args.town).get_map(),
                                                  args.waypoint_distance)
    # 2. The plan; an existing capture folder must hold the same plan (resume) unless --force.
    plan = plan_capture(args.town, waypoints, cfg)
    old = out / PLAN_FILE
    if old.is_file() and inputfiles.read_json(old).get("frames") != plan["frames"]:
        if not args.force:
            raise UserError(f"{old}: a capture of another plan (town, options or protocol differ); pass --force "
                            "to start over, or another --out")
        for given in (args.waypoints, args.xodr):  # starting over deletes OUT: never a file this run reads
            if given and inputfiles.inside(given, out):
                raise UserError(f"{given}: lies inside {out}, which --force would delete before reading it; "
                                "copy it out of OUT first")
        shutil.rmtree(out)
    if not args.waypoints:
        outputfiles.write_json(out / WAYPOINTS_FILE, waypoints_document(args.town, waypoints, args.waypoint_distance))
    outputfiles.write_json(old, plan)
    nground = sum(r["kind"] == "ground" for r in plan["frames"])
    print(f"planned {old}: {len(plan['plan']['lanes'])} lanes, {nground} ground and "
          f"{len(plan['frames']) - nground} aerial frames ({args.town}, protocol {proto.data_ref})")
    if args.plan_only:
        return 0
    # 3. Render what is not on disk yet; capture.json last.
    done, kept = carla_live.capture(plan, out, server, progress=not args.no_progress)
    print(f"wrote {out / 'capture.json'}: {done} frames rendered, {kept} kept from an earlier run; "
          f"import with: skyeyes-bench data import-carla {out} DATASET")
    return 0


def _import_carla(args) -> int:
    from ..data.importers import import_carla

    out, scenes = import_carla(args.src, args.out, protocol=args.protocol, split=args.split, force=args.force,
                               progress=not args.no_progress)
    print(_imported(out, scenes))
    return 0


def _import_matrixcity(args) -> int:
    from ..data.importers import import_matrixcity

    out, scenes, meta = import_matrixcity(
        args.src, args.out, protocol=args.protocol, town=args.town, split=args.split, pose_format=args.pose_format,
        convention=args.convention, depth_root=args.depth_root, aerial_radius_m=args.aerial_radius,
        regions=_regions(args.region), include=args.include or None, force=args.force,
        progress=not args.no_progress)
    print(_imported(out, scenes))
    for d in meta["protocol_differences"]:
        print(f"  differs from the protocol: {d}")
    return 0


def _regions(values: list[str]) -> dict[str, list[str]] | None:
    """--region TOWN=BLOCK[,BLOCK...] options -> {town: [block, ...]} (None when there are none)."""
    from ..errors import UserError

    out: dict[str, list[str]] = {}
    for v in values:
        town, eq, blocks = v.partition("=")
        names = [b for b in blocks.split(",") if b]
        if not eq or not town or not names:
            raise UserError(f"--region {v!r}: expected TOWN=BLOCK[,BLOCK...], e.g. region5=block_10")
        if town in out:
            raise UserError(f"--region {v!r}: region {town!r} given twice")
        out[town] = names
    return out or None


def _imported(out: Path, scenes) -> str:
    """One line: what an importer wrote."""
    nseq = sum(len({f.sequence for f in s.ground}) for s in scenes)
    return (f"wrote {out}: {len(scenes)} scenes, {nseq} sequences, {sum(len(s.ground) for s in scenes)} ground "
            f"frames, {sum(len(s.aerial) for s in scenes)} aerial frames")


#: Action name -> function (`register` adds a parser for each).
ACTIONS = {"check": _check, "synthtown": _synthtown, "gallery": _gallery, "capture-carla": _capture_carla,
           "import-carla": _import_carla,
           "import-matrixcity": _import_matrixcity}
