"""`relight`: the command-line entry point.

Each subcommand lives in `pipeline/commands/<name>.py` and exposes `add_parser(subparsers)` and
`run(args) -> int`. Options mean the same on every subcommand (see `pipeline.commands.common`).

Failures are one line on stderr, never a traceback: bad input (`RelightError`) exits 2; an
unexpected error exits 1 with a line naming the subcommand and a log file holding the traceback
(`--debug` prints the traceback instead).
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import logging
import os
import sys
import tempfile
import traceback
from pathlib import Path

from pipeline import __version__
from pipeline.errors import RelightError
from pipeline.heap import use_one_heap_arena

# Subcommand modules, in the order `relight --help` lists them.
COMMANDS = (
    "demo",
    "scenes",
    "info",
    "bake",
    "render",
    "serve",
    "reference",
    "solve",
    "trace_bench",
    "bench_direct",
    "bench",
)


# How log records read on stderr (a warning: 'relight: WARNING: ...').
LOG_FORMAT = "relight: %(levelname)s: %(message)s"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="relight",
        description="Bake a USD shot once, then relight it in milliseconds.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    parser.add_argument("--version", action="version", version=f"relight {__version__}")
    parser.add_argument(
        "--debug",
        action="store_true",
        help="print the traceback of an unexpected error (default: write it to a log file)",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        module = importlib.import_module(f"pipeline.commands.{name}")
        module.add_parser(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    use_one_heap_arena()  # before any worker thread: see pipeline/heap.py
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format=LOG_FORMAT)
    try:
        return int(args.run(args) or 0)
    except RelightError as error:
        print(f"relight: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("relight: interrupted", file=sys.stderr)
        return 130
    except Exception as error:
        if isinstance(error, OSError) and error.filename is not None:
            # A path that cannot be read or written (a file where a folder is due, no permission): input.
            print(f"relight: error: {error.filename}: {error.strerror}", file=sys.stderr)
            return 2
        return _internal_error(args, argv, error)  # anything else is our bug: one line, the traceback kept


def _internal_error(args: argparse.Namespace, argv: list[str] | None, error: BaseException) -> int:
    """Report an unexpected error of subcommand `args.command` in one line (exit status 1), its
    traceback written to a log file the line names, or printed with --debug."""
    step = args.command
    summary = f"{type(error).__name__}: {error}".splitlines()[0] if str(error) else type(error).__name__
    if args.debug:
        traceback.print_exception(error)
        print(f"relight: internal error in '{step}': {summary}", file=sys.stderr)
    else:
        log = write_traceback_log(step, argv if argv is not None else sys.argv[1:], error)
        print(
            f"relight: internal error in '{step}': {summary} (traceback in {log}; --debug prints it)", file=sys.stderr
        )
    return 1


def write_traceback_log(step: str, argv: list[str], error: BaseException) -> Path:
    """Write `error`'s traceback, with the command line, to a new log file under the
    temporary directory's `relight-logs/` (the output directory may be what failed); its path.

    Args:
        step: the subcommand that failed; argv: its command line.
    """
    directory = Path(tempfile.gettempdir()) / "relight-logs"
    directory.mkdir(parents=True, exist_ok=True)
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    descriptor, name = tempfile.mkstemp(prefix=f"relight-{step}-{stamp}-", suffix=".log", dir=directory)
    with os.fdopen(descriptor, "w") as log:
        log.write(f"relight {' '.join(argv)}\n\n{''.join(traceback.format_exception(error))}")
    return Path(name)


if __name__ == "__main__":
    sys.exit(main())
