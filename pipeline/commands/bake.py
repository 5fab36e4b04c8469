"""`relight bake`: bake a shot's relighting cache."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from pipeline.bake.direct import bake_direct
from pipeline.bake.gather.bake import GatherSettings, bake_gather
from pipeline.bake.transfer.bake import TransferSettings, bake_transfer
from pipeline.commands.common import add_camera_options
from pipeline.errors import RelightError
from pipeline.scene import find_camera, load_scene

METHODS = ("direct", "transfer", "gather")


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
    transfer = parser.add_argument_group("transfer (--method transfer)")
    defaults = TransferSettings()
    transfer.add_argument("--gathers", type=int, default=defaults.num_gathers, metavar="G",
                          help=f"gather samples, a power of 4 (default {defaults.num_gathers})")
    transfer.add_argument("--coefficients", type=int, default=defaults.num_coefficients, metavar="K",
                          help=f"wavelet coefficients kept per final-gather row (default {defaults.num_coefficients})")
    transfer.add_argument("--bounces", type=int, default=defaults.num_bounces, metavar="B",
                          help="indirect bounces; 1 bakes the final gather only (default 1)")
    transfer.add_argument("--bounce-coefficients", type=int, default=defaults.num_bounce_coefficients, metavar="K",
                          help=f"coefficients kept per gather-to-gather row (default {defaults.num_bounce_coefficients})")
    transfer.add_argument("--quantize", action="store_true",
                          help="store coefficients as 8 bits with a per-row scale and offset (default float16)")
    gather = parser.add_argument_group("gather (--method gather)")
    gather_defaults = GatherSettings()
    gather.add_argument("--directions", type=int, default=gather_defaults.num_directions, metavar="N",
                        help=f"QMC hemisphere directions per view representative (default {gather_defaults.num_directions})")
    gather.add_argument("--clusters", type=int, default=gather_defaults.num_clusters, metavar="K",
                        help=f"clustered gathers per view representative (default {gather_defaults.num_clusters})")
    gather.add_argument("--representatives", type=int, default=None, metavar="R",
                        help="view representatives (default: 40,000 at 400x400, scaled with the pixel count)")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    if args.supersampling < 1 or args.texture_samples < 1:
        raise RelightError(f"--supersampling and --texture-samples must be >= 1, "
                           f"got {args.supersampling} and {args.texture_samples}")
    start = time.perf_counter()
    scene = load_scene(args.scene, time=args.time, width=args.width, height=args.height)
    camera = find_camera(scene, args.camera)
    stem = args.stem or Path(args.scene).name.split(".")[0]
    if args.method == "transfer":
        settings = TransferSettings(num_gathers=args.gathers, num_coefficients=args.coefficients,
                                    num_bounces=args.bounces, num_bounce_coefficients=args.bounce_coefficients,
                                    encoding="uint8" if args.quantize else "float16")
        try:
            settings.check()
        except ValueError as error:
            raise RelightError(f"bake --method transfer: {error}") from None
        layer = bake_transfer(scene, camera, args.out, stem, args.supersampling, args.texture_samples,
                              time_code=args.time, settings=settings)
    elif args.method == "gather":
        settings = GatherSettings(num_directions=args.directions, num_clusters=args.clusters,
                                  num_representatives=args.representatives)
        try:
            settings.check()
        except ValueError as error:
            raise RelightError(f"bake --method gather: {error}") from None
        layer = bake_gather(scene, camera, args.out, stem, args.supersampling, args.texture_samples,
                            time_code=args.time, settings=settings)
    else:
        layer = bake_direct(scene, camera, args.out, stem, args.supersampling, args.texture_samples,
                            time_code=args.time)
    print(f"{layer}: {args.method} cache of {args.camera} at {camera.width}x{camera.height} "
          f"(supersampling {args.supersampling}) in {time.perf_counter() - start:.1f} s")
    return 0
