"""`skyeyes-bench submission template`: the submission format by example."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("submission", help="write a submission skeleton (the format by example)",
                       description="Submissions: submission.json plus one 8-bit RGB PNG per ground camera "
                       "of every test scene at <SUB>/<scene>/<frame file> (see docs/evaluate.md).")
    p.set_defaults(group_parser=p)
    ps = p.add_subparsers(title="actions", metavar="ACTION")
    q = ps.add_parser("template", help="write submission.json and the list of expected frames",
                      description="Write a valid skeleton: submission.json and EXPECTED_FRAMES.txt (path, "
                      "size, sequence, index of every frame to render); with --from-ground-truth a complete "
                      "submission made of the ground-truth frames, which scores perfectly.")
    q.add_argument("--data", required=True, metavar="DIR", help="dataset folder (holds dataset.json)")
    q.add_argument("--out", required=True, metavar="SUB", help="submission folder to create")
    q.add_argument("--from-ground-truth", action="store_true", help="copy the ground-truth frames in")
    q.add_argument("--force", action="store_true", help="replace an existing SUB")
    q.set_defaults(handler="skyeyes_bench.commands._submission_impl:template_cmd")
