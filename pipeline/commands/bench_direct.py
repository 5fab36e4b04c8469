"""`relight bench-direct`: what each kind of light edit costs the direct relighter."""

from __future__ import annotations

import argparse
import os

import torch

from pipeline.benchmarks.direct import format_table, run_benchmark, write_csv
from pipeline.commands.common import add_device_option
from pipeline.errors import RelightError
from pipeline.scenes import SCENES
from relight_torch.direct.settings import RelightSettings


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "bench-direct",
        help="benchmark direct relighting edits (re-shade, move, shaping, colour)",
        description="Bake a bundled scene, then time renders after edits that invalidate different "
        "stages of the relighter, with rigs of 1, 4 and 16 lights; print a table of median "
        "wall and CPU milliseconds, passes run, cache sizes and peak memory, then the table "
        "of edit kinds (colour, shaping, move, link) and what each recomputes.",
    )
    parser.add_argument("--scene", default="glossy", choices=sorted(SCENES), help="bundled scene (default: glossy)")
    parser.add_argument("--width", type=int, default=640, metavar="W", help="image width (default: 640)")
    parser.add_argument("--height", type=int, default=480, metavar="H", help="image height (default: 480)")
    parser.add_argument(
        "--supersampling", type=int, default=1, metavar="S", help="S x S sub-samples per pixel (default: 1)"
    )
    add_device_option(parser)
    parser.add_argument("--repeats", type=int, default=9, metavar="N", help="timed edits per row (default: 9)")
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        metavar="K",
        help="torch CPU threads (default: the CPUs this process may use)",
    )
    parser.add_argument(
        "--area-samples",
        type=int,
        default=RelightSettings.area_samples,
        metavar="S",
        help=f"samples per point of a large area light (default: {RelightSettings.area_samples})",
    )
    parser.add_argument(
        "--full-sampling-angle",
        type=float,
        default=10.0,
        metavar="DEG",
        help="angular radius from which a light gets all its samples; smaller lights get "
        "fewer (default: 10; 0: all lights get --area-samples)",
    )
    parser.add_argument(
        "--accuracy", action="store_true", help="also report the PSNR against every light at --area-samples (slow)"
    )
    parser.add_argument("-o", "--out", metavar="OUT.csv", help="also write the table as CSV")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    for option in ("width", "height", "supersampling", "repeats", "threads", "area_samples"):
        value = getattr(args, option)
        if value is not None and value < 1:
            raise RelightError(f"--{option.replace('_', '-')} must be at least 1, got {value}")
    if args.device == "cuda" and not torch.cuda.is_available():
        raise RelightError("--device cuda: CUDA is not available on this machine")
    torch.set_num_threads(args.threads or len(os.sched_getaffinity(0)))
    settings = RelightSettings(area_samples=args.area_samples, full_sampling_angle=args.full_sampling_angle)
    report = run_benchmark(
        args.scene,
        args.width,
        args.height,
        args.supersampling,
        args.device,
        args.repeats,
        settings,
        accuracy=args.accuracy,
    )
    print(format_table(report))
    if args.out:
        write_csv(report, args.out)
    return 0
