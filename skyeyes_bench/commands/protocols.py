"""`skyeyes-bench protocols list|show`."""

from __future__ import annotations

import json


def register(sub) -> None:
    p = sub.add_parser("protocols", help="list and show the versioned evaluation protocols",
                       description="Versioned evaluation protocols (protocols/<id>/v<N>.toml).")
    p.set_defaults(run=run, group_parser=p)
    ps = p.add_subparsers(title="actions", dest="action", metavar="ACTION")
    q = ps.add_parser("list", help="one 'id@N<TAB>title' line per protocol version")
    q.add_argument("--json", action="store_true", help="print JSON instead: [{\"ref\", \"title\", \"sha256\", "
                   "\"file\"}, ...]")
    q = ps.add_parser("show", help="print a resolved protocol with its sha256",
                      description="Print the resolved protocol (TOML-like) with its canonical sha256.")
    q.add_argument("ref", metavar="ID[@N]", help="protocol id, optionally with @version (default: latest)")
    q.add_argument("--json", action="store_true", help="print JSON instead")


def run(args) -> int:
    return ACTIONS[args.action](args)


def _list(args) -> int:
    from ..protocol import list_protocols

    protocols = list_protocols()
    if args.json:
        print(_json([{"ref": p.ref, "title": p.title, "sha256": p.sha256, "file": p.path} for p in protocols]))
        return 0
    for p in protocols:
        print(f"{p.ref}\t{p.title}")
    return 0


def _json(doc) -> str:
    """JSON as people read it: "FID∞", not "FID\\u221e" (still valid JSON, UTF-8)."""
    return json.dumps(doc, indent=2, ensure_ascii=False)


def _toml_value(v) -> str:
    if isinstance(v, str):  # a TOML basic string; TOML is UTF-8, so "∞" stays "∞"
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(v)


def _show(args) -> int:
    import dataclasses
    from pathlib import Path

    from ..protocol import VAL_FILE, load_protocol

    p = load_protocol(args.ref)
    d = p.to_dict()
    val = dataclasses.asdict(p.val) if p.val is not None else None
    if args.json:
        print(_json({"ref": p.ref, "sha256": p.sha256, "file": p.path, **d, "val": val}))
        return 0
    print(f"# {p.ref}  sha256 {p.sha256}\n# file: {p.path}")
    for k in ("id", "version", "title", "description", "reference"):
        print(f"{k} = {_toml_value(d[k])}")
    for section in ("data", "capture"):
        print(f"\n[{section}]")
        for k, v in d[section].items():
            print(f"{k} = {_toml_value(v)}")
    for name, m in d["metrics"].items():
        print(f"\n[metrics.{name}]")
        for k, v in m.items():
            print(f"{k} = {_toml_value(v)}")
    print("\n[statistics]")
    for k, v in d["statistics"].items():
        print(f"{k} = {_toml_value(v)}")
    if val is None:
        print("\n# no validation split declared: settings cannot be chosen on this protocol's data")
    else:
        print(f"\n# the validation split of every {p.id} version ({Path(p.path).parent / VAL_FILE}; where settings "
              "are chosen, never ranked; not part of the sha256)\n[val]")
        for k, v in val.items():
            print(f"{k} = {_toml_value(v)}")
    return 0


#: Action name -> function (`register` adds a parser for each).
ACTIONS = {"list": _list, "show": _show}
