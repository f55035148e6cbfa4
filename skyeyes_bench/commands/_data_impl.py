from __future__ import annotations

import json
import sys

from ..data.layout import open_dataset


def check_cmd(args) -> int:
    ds = open_dataset(args.root, check_pixels=not args.quick, progress=not args.quick and sys.stderr.isatty())
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
