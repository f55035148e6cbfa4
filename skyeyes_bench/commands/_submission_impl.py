from __future__ import annotations

from ..data.layout import open_dataset
from ..submission import EXPECTED_FILE, expected_frames, write_template


def template_cmd(args) -> int:
    ds = open_dataset(args.data)
    out = write_template(ds, args.out, from_ground_truth=args.from_ground_truth, overwrite=args.force)
    n = len(expected_frames(ds))
    if args.from_ground_truth:
        print(f"{out}: complete submission of the {n} ground-truth frames (evaluate it: "
              f"`skyeyes-bench evaluate {out} --data {args.data}`)")
    else:
        print(f"{out}: submission.json and {EXPECTED_FILE} ({n} frames to render)")
    return 0
