"""Subcommand groups. Each module imports argparse only and exposes `register(subparsers)`;
handlers are `"module:function"` strings loaded when the command runs."""
