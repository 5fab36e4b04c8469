"""`relight reference`: render the ground truth with the path tracer."""

from __future__ import annotations

import argparse

import numpy as np

from pipeline.commands.common import add_camera_options, add_lights_option, add_materials_option
from pipeline.errors import RelightError
from pipeline.progress import progress_bar
from pipeline.reference.path_tracer import FULL_FRAME_BOUNCES, PathTracer, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from relight_torch.io.exr import write_exr


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "reference",
        help="render a reference image with the path tracer",
        description="Unbiased path tracing (NEE + MIS) of a USD shot's full frame (every bounce by default) "
        "to a linear float EXR with R, G, B and the per-pixel variance of the estimate as variance.R/G/B.",
    )
    parser.add_argument("scene", metavar="SCENE", help="USD stage (.usda, .usdc, .usdz)")
    add_camera_options(parser)
    add_lights_option(parser)
    add_materials_option(parser, ", composed over the shot (what `relight render --materials` relights)")
    parser.add_argument("-o", "--out", required=True, metavar="OUT.exr", help="output EXR")
    parser.add_argument("--spp", type=int, default=64, help="samples per pixel (default 64)")
    parser.add_argument(
        "--max-bounces",
        type=int,
        default=FULL_FRAME_BOUNCES,
        help="indirect bounces, for a slice of the light transport: 0 = direct light only, 1 = one "
        f"bounce (default {FULL_FRAME_BOUNCES}: the full frame, every bounce; Russian roulette "
        "ends paths long before the cap)",
    )
    parser.add_argument("--seed", type=int, default=0, help="random seed; same seed, same image (default 0)")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    scene = load_scene(
        args.scene,
        time=args.time,
        lights_layer=args.lights,
        materials_layer=args.materials,
        width=args.width,
        height=args.height,
    )
    camera = find_camera(scene, args.camera)
    if args.spp < 1 or args.max_bounces < 0:
        raise RelightError(f"--spp must be >= 1 and --max-bounces >= 0 (got {args.spp}, {args.max_bounces})")
    settings = ReferenceSettings(spp=args.spp, max_bounces=args.max_bounces, seed=args.seed)
    tracer = PathTracer(scene, settings)
    with progress_bar("reference", camera.width * camera.height * settings.spp, unit="path") as update:
        image = tracer.render(camera, progress=update)
    channels = {c: image.mean[..., i] for i, c in enumerate("RGB")}
    channels.update({f"variance.{c}": image.variance[..., i] for i, c in enumerate("RGB")})
    write_exr(
        args.out,
        channels,
        {
            "relight:spp": settings.spp,
            "relight:maxBounces": settings.max_bounces,
            "relight:seed": settings.seed,
            "relight:source": str(args.scene),
            "relight:camera": args.camera,
            "relight:seconds": float(image.seconds),
        },
    )
    rate = image.num_paths / max(image.seconds, 1e-9)
    print(
        f"{args.out}: {camera.width}x{camera.height}, {settings.spp} spp, max bounces {settings.max_bounces}, "
        f"{image.seconds:.1f} s ({rate / 1e6:.2f} M paths/s), "
        f"mean noise sigma {float(np.sqrt(image.variance).mean()):.4g}"
    )
    return 0
