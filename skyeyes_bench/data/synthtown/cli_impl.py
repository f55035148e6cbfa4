"""Handlers of `data synthtown` and `data gallery` (imported only when they run)."""

from __future__ import annotations

from pathlib import Path

from ...errors import UserError


def synthtown_cmd(args) -> int:
    from ... import paths
    from .generate import dataset_name, ensure_dataset, generate_dataset

    if args.seed < 0:
        raise UserError(f"--seed {args.seed}: expected an integer >= 0")
    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers {args.workers}: expected an integer >= 1")
    if args.out is None and not args.force and args.workers is None:
        root = paths.data_dir() / dataset_name(args.preset, args.seed)
        existed = (root / "dataset.json").is_file()
        root = ensure_dataset(args.preset, args.seed, progress=not args.quiet)
        print(f"{'exists' if existed else 'wrote'} {root}")
        return 0
    out = Path(args.out) if args.out else paths.data_dir() / dataset_name(args.preset, args.seed)
    generate_dataset(out, args.preset, args.seed, overwrite=args.force, progress=not args.quiet, workers=args.workers)
    print(f"wrote {out}")
    return 0


def gallery_cmd(args) -> int:
    from .gallery import tiles_from_dataset, tiles_rendered, write_gallery

    if args.rows < 1 or args.size < 16:
        raise UserError("gallery: --rows must be >= 1 and --size >= 16")
    if args.dataset:
        tiles = tiles_from_dataset(Path(args.dataset), args.rows)
    else:
        tiles = tiles_rendered(args.preset, args.seed, args.rows, args.size)
    out = write_gallery(tiles, Path(args.out))
    print(f"wrote {out}")
    return 0
