"""One module per subcommand: `register(subparsers)` adds its parser (argparse only at import) and
`run(args)` does the work, importing what it needs then. A group (`data`, `protocols`, `weights`,
`submission`) registers its actions in the same module and `run` dispatches on `args.action`."""
