from __future__ import annotations

import json

from ..protocol import list_protocols, load_protocol


def list_cmd(args) -> int:
    for p in list_protocols():
        print(f"{p.ref}\t{p.title}")
    return 0


def _toml_value(v) -> str:
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(v)


def show_cmd(args) -> int:
    p = load_protocol(args.ref)
    d = p.to_dict()
    if args.json:
        print(json.dumps({"ref": p.ref, "sha256": p.sha256, "file": p.path, **d}, indent=2))
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
    return 0
