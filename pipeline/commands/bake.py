"""`relight bake`: bake a shot's relighting cache."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from pipeline.bake.direct import bake_direct
from pipeline.commands.common import add_camera_options
from pipeline.errors import RelightError
from pipeline.scene import find_camera, load_scene

METHODS = ("direct",)


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "bake", help="bake a relighting cache for a shot and camera",
        description="Trace the shot once and write OUT/<stem>.relight.usda with its payload files "
                    "(deep framebuffer EXR, occluders). Files are written atomically.")
    parser.add_argument("scene", metavar="SCENE", help="USD stage (.usda, .usdc, .usdz)")
    add_camera_options(parser)
    parser.add_argument("--out", "-o", required=True, metavar="DIR", help="output directory")
    parser.add_argument("--method", default="direct", choices=METHODS,
                        help="relighting method to bake for (default: direct)")
    parser.add_argument("--supersampling", type=int, default=2, metavar="S",
                        help="S x S sub-samples per pixel, shaded separately and box-filtered (default 2)")
    parser.add_argument("--texture-samples", type=int, default=2, metavar="T",
                        help="T x T material samples per sub-sample, averaged: texture filtering (default 2)")
    parser.add_argument("--stem", help="file name stem (default: the scene file's stem)")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    if args.supersampling < 1 or args.texture_samples < 1:
        raise RelightError(f"--supersampling and --texture-samples must be >= 1, "
                           f"got {args.supersampling} and {args.texture_samples}")
    start = time.perf_counter()
    scene = load_scene(args.scene, time=args.time, width=args.width, height=args.height)
    camera = find_camera(scene, args.camera)
    stem = args.stem or Path(args.scene).name.split(".")[0]
    layer = bake_direct(scene, camera, args.out, stem, args.supersampling, args.texture_samples, time_code=args.time)
    print(f"{layer}: {args.method} cache of {args.camera} at {camera.width}x{camera.height} "
          f"(supersampling {args.supersampling}) in {time.perf_counter() - start:.1f} s")
    return 0
