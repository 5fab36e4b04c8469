"""`relight bench`: every relighting method's speed against its accuracy, with the path tracer beside."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import torch

from pipeline.bake.methods import bake_methods
from pipeline.benchmarks.bench import time_to_quality
from pipeline.benchmarks.bench.runner import BenchConfig, run_bench
from pipeline.commands.common import add_device_option
from pipeline.errors import RelightError
from pipeline.scenes import SCENES


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "bench",
        help="run every relighting method's sweep against the reference; CSV, JSON and charts",
        description="Bake each method's parameter sweep on the bundled scenes, relight under the example "
        "light edits, compare with the reference path tracer at the matching bounce count and "
        "write OUT/bench.csv, OUT/bench.json, OUT/summary.txt (each method's best speed-up over "
        "the path tracer at equal PSNR), OUT/speed_accuracy.png and OUT/params_<method>.png. "
        "References are cached in OUT/references and re-used by a later run into OUT.",
    )
    parser.add_argument("--out", "-o", required=True, metavar="DIR", help="output directory")
    parser.add_argument(
        "--quick", action="store_true", help="small grids on the Cornell box at 24x24 (seconds; what the tests run)"
    )
    parser.add_argument(
        "--scenes",
        nargs="+",
        choices=sorted(SCENES),
        metavar="SCENE",
        help="bundled scenes (default: all; --quick: cornell_box)",
    )
    methods = list(bake_methods())
    parser.add_argument(
        "--methods",
        nargs="+",
        choices=methods,
        metavar="METHOD",
        help=f"methods to run (default: all of {', '.join(methods)})",
    )
    parser.add_argument(
        "--edits",
        nargs="+",
        metavar="EDIT",
        help="example light edits to relight under besides the shot's lights (default: all)",
    )
    parser.add_argument("--width", type=int, metavar="W", help="image width (default 160; --quick 24)")
    parser.add_argument("--height", type=int, metavar="H", help="image height (default 120; --quick 24)")
    parser.add_argument("--spp", type=int, metavar="N", help="reference samples per pixel (default 256; --quick 32)")
    parser.add_argument(
        "--curve-spp",
        type=int,
        nargs="+",
        metavar="N",
        help="spp of the path-tracer renders fitted for the comparison rows (default 1 2 4 8 16; --quick 1 4)",
    )
    parser.add_argument("--repeats", type=int, metavar="N", help="timed light moves per relight time (default 7)")
    parser.add_argument(
        "--progressive",
        action="store_true",
        help="instead of the sweep, the time-to-quality run: PSNR against time after each light edit for the "
        "relighter's progressive frames (shot and direct caches of the Cornell box) and for the path tracers, "
        "the project's and Mitsuba 3's, re-rendering from the same start; OUT/time_to_quality.{csv,md,png} "
        "(default size 640x480, reference 512 spp)",
    )
    time_to_quality.add_progressive_options(parser)
    add_device_option(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    if args.progressive:
        return time_to_quality.run(time_to_quality.with_defaults(args))
    for option in ("width", "height", "spp", "repeats"):
        value = getattr(args, option)
        if value is not None and value < 1:
            raise RelightError(f"--{option} must be at least 1, got {value}")
    if args.device == "cuda" and not torch.cuda.is_available():
        raise RelightError("--device cuda: CUDA is not available on this machine")
    overrides = {
        key: value
        for key, value in (
            ("width", args.width),
            ("height", args.height),
            ("spp", args.spp),
            ("repeats", args.repeats),
            ("device", args.device),
        )
        if value is not None
    }
    if args.scenes:
        overrides["scenes"] = tuple(args.scenes)
    if args.methods:
        overrides["methods"] = tuple(args.methods)
    if args.edits:
        overrides["edits"] = tuple(args.edits)
    if args.curve_spp:
        if min(args.curve_spp) < 1:
            raise RelightError(f"--curve-spp must be at least 1, got {args.curve_spp}")
        overrides["curve_spp"] = tuple(args.curve_spp)
    out = Path(args.out)
    config = (
        BenchConfig.quick_run(out, **overrides) if args.quick else dataclasses.replace(BenchConfig(out), **overrides)
    )
    result = run_bench(config, log=lambda line: print(line, flush=True))
    print((out / "summary.txt").read_text(), end="")
    for path in result.files:
        print(path)
    return 0
