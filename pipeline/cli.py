"""`relight`: the command-line entry point.

Each subcommand lives in `pipeline/commands/<name>.py` and exposes `add_parser(subparsers)` and
`run(args) -> int`. Options mean the same on every subcommand (see `pipeline.commands.common`).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from pipeline import __version__
from pipeline.errors import RelightError

# Subcommand modules, in the order `relight --help` lists them.
COMMANDS = ("demo", "scenes", "info", "bake", "render", "reference", "trace_bench", "bench_direct", "bench")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="relight",
        description="Bake a USD shot once, then relight it in milliseconds.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    parser.add_argument("--version", action="version", version=f"relight {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        module = importlib.import_module(f"pipeline.commands.{name}")
        module.add_parser(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="relight: %(levelname)s: %(message)s",
    )
    try:
        return int(args.run(args) or 0)
    except RelightError as error:
        print(f"relight: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("relight: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
