from __future__ import annotations

import json
import sys

from .. import paths
from ..metrics import weights as W
from ..metrics.extractors import EXTRACTORS, get_extractor


def status_cmd(args) -> int:
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


def fetch_cmd(args) -> int:
    W.fetch(log=lambda s: print(s, file=sys.stderr))
    return 0


def add_cmd(args) -> int:
    for f in args.files:
        W.add(f, log=lambda s: print(s, file=sys.stderr))
    return 0
