"""`skyeyes-bench` command line. A thin argparse front over one module per subcommand,
`skyeyes_bench.commands.<name>`, with `register(subparsers)` (argparse only) and `run(args)`
(which imports numpy, torch and the implementation modules when the command runs), so
`--help` never imports torch. A group's actions (`data check`, ...) live in its module.

Exit codes: 0 success, 2 invalid input or usage (one line on stderr), 1 internal error.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from . import __version__

#: Subcommands (modules of `skyeyes_bench.commands`), in the order `--help` lists them.
COMMANDS = [
    "protocols",
    "data",
    "weights",
    "submission",
    "evaluate",
    "compare",
    "merge",
    "seeds",
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
        importlib.import_module(f"skyeyes_bench.commands.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    from .errors import UserError

    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    if getattr(args, "action", "") is None:  # a group without its action: show that group's help
        args.group_parser.print_help()
        return 2
    try:
        rc = args.run(args)
        return 0 if rc is None else int(rc)
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
