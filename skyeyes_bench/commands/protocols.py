"""`skyeyes-bench protocols list|show`."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("protocols", help="list and show the versioned evaluation protocols",
                       description="Versioned evaluation protocols (protocols/<id>/v<N>.toml).")
    p.set_defaults(group_parser=p)
    ps = p.add_subparsers(title="actions", metavar="ACTION")
    q = ps.add_parser("list", help="one 'id@N<TAB>title' line per protocol version")
    q.set_defaults(handler="skyeyes_bench.commands._protocols_impl:list_cmd")
    q = ps.add_parser("show", help="print a resolved protocol with its sha256",
                      description="Print the resolved protocol (TOML-like) with its canonical sha256.")
    q.add_argument("ref", metavar="ID[@N]", help="protocol id, optionally with @version (default: latest)")
    q.add_argument("--json", action="store_true", help="print JSON instead")
    q.set_defaults(handler="skyeyes_bench.commands._protocols_impl:show_cmd")
