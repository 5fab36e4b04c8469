"""One module per `relight` subcommand: `add_parser(subparsers)` registers it, setting `run`."""
