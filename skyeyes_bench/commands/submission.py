"""`skyeyes-bench submission template`: the submission format by example."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("submission", help="write a submission skeleton (the format by example)",
                       description="Submissions: submission.json plus one 8-bit RGB PNG per ground camera "
                       "of every test scene at <SUB>/<scene>/<frame file> (see docs/evaluate.md).")
    p.set_defaults(run=run, group_parser=p)
    ps = p.add_subparsers(title="actions", dest="action", metavar="ACTION")
    q = ps.add_parser("template", help="write submission.json and the list of expected frames",
                      description="Write a valid skeleton: submission.json and EXPECTED_FRAMES.txt (path, "
                      "size, sequence, index of every frame to render); with --from-ground-truth a complete "
                      "submission made of the ground-truth frames, which scores perfectly.")
    q.add_argument("--data", required=True, metavar="DIR", help="dataset folder (holds dataset.json)")
    q.add_argument("--out", required=True, metavar="SUB", help="submission folder to create")
    q.add_argument("--from-ground-truth", action="store_true", help="copy the ground-truth frames in")
    q.add_argument("--split", choices=("test", "val"), default="test",
                   help="the frames of the test split (default) or of the validation split, where settings are "
                   "chosen (the dataset's 'val' split, or the part of its train towns its protocol declares)")
    q.add_argument("--force", action="store_true", help="replace an existing SUB")


def run(args) -> int:
    return ACTIONS[args.action](args)


def _template(args) -> int:
    from ..data.layout import open_dataset
    from ..protocol import current_for_data, load_protocol
    from ..splits import scored_view
    from ..submission import EXPECTED_FILE, expected_frames, write_template

    ds = open_dataset(args.data)
    # the split checked as evaluate checks it (a missing or empty test split: one line, nothing written)
    ds = scored_view(ds, args.split, load_protocol(current_for_data(ds.protocol)) if args.split != "test" else None)
    out = write_template(ds, args.out, from_ground_truth=args.from_ground_truth, overwrite=args.force)
    n = len(expected_frames(ds))
    if args.from_ground_truth:
        print(f"{out}: complete submission of the {n} ground-truth frames of the {ds.scored} split (evaluate it: "
              f"`skyeyes-bench evaluate {out} --data {args.data}`)")
    else:
        print(f"{out}: submission.json and {EXPECTED_FILE} ({n} frames of the {ds.scored} split to render)")
    return 0


#: Action name -> function (`register` adds a parser for each).
ACTIONS = {"template": _template}
