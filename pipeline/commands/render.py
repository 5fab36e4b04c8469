"""`relight render`: relight a baked cache under the shot's lights and a layer of edits."""

from __future__ import annotations

import argparse
import time

from pipeline.commands.common import add_device_option, add_lights_option
from relight_torch.io.exr import write_rgb_exr
from relight_torch.io.preview import write_png
from relight_torch.transfer.open import open_cache_relighter


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "render", help="relight a baked cache",
        description="Relight CACHE (a <stem>.relight.usda) with the shot's lights, with LAYER's light "
                    "edits composed over them, and write a linear float EXR (R, G, B).")
    parser.add_argument("cache", metavar="CACHE", help="cache layer written by `relight bake`")
    add_lights_option(parser)
    add_device_option(parser)
    parser.add_argument("-o", "--out", required=True, metavar="OUT.exr", help="output EXR")
    parser.add_argument("--png", metavar="OUT.png", help="also write an 8-bit sRGB preview")
    parser.add_argument("--shadows", default="embree", choices=("embree", "shadowmaps"),
                        help="exact Embree shadow rays (CPU) or torch shadow maps (default: embree)")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    relighter = open_cache_relighter(args.cache, device=args.device, shadows=args.shadows, lights_layer=args.lights)
    image = relighter.render().cpu().numpy()
    write_rgb_exr(args.out, image)
    if args.png:
        write_png(args.png, image)
    print(f"{args.out}: {image.shape[1]}x{image.shape[0]}, {len(relighter.lights)} lights, "
          f"{time.perf_counter() - start:.2f} s including load")
    return 0
