"""`skyeyes-bench` command line. A thin argparse front: each subcommand group lives in
`skyeyes_bench.commands.<name>` (argparse only at import time) and names its handler as a lazy
`"module:function"` string, so `--help` never imports torch.

Exit codes: 0 success, 2 invalid input or usage (one line on stderr), 1 internal error.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from . import __version__

#: Subcommand groups, in the order `--help` lists them.
COMMANDS = [
    "protocols",
    "data",
    "weights",
    "submission",
    "evaluate",
    "compare",
    "merge",
    "leaderboard",
    "reproduce",
]


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, exit 2 (argparse prints usage + error by default)
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="skyeyes-bench",
        description="Benchmark and reference methods for aerial-to-ground view synthesis "
        "(Skyeyes, WACV 2025). Every subcommand has its own --help.",
    )
    parser.add_argument("--version", action="version", version=f"skyeyes-bench {__version__}")
    sub = parser.add_subparsers(title="subcommands", dest="command", metavar="COMMAND", parser_class=_Parser)
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"skyeyes_bench.commands.{name}")
        except ModuleNotFoundError as e:
            if e.name == f"skyeyes_bench.commands.{name}":
                continue  # group not built yet
            raise
        module.register(sub)
    return parser


def _run(handler: str, args: argparse.Namespace) -> int:
    module, _, attr = handler.partition(":")
    fn = getattr(importlib.import_module(module), attr)
    rc = fn(args)
    return 0 if rc is None else int(rc)


def main(argv: list[str] | None = None) -> int:
    from .errors import UserError

    parser = build_parser()
    args = parser.parse_args(argv)
    handler = getattr(args, "handler", None)
    if handler is None:
        # A group without its sub-subcommand: show that group's help.
        (getattr(args, "group_parser", None) or parser).print_help()
        return 2 if args.command else 0
    try:
        return _run(handler, args)
    except UserError as e:
        print(f"skyeyes-bench: error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print("skyeyes-bench: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
