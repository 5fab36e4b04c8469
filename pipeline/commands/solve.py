"""`relight solve`: light settings that make a cache's frame look like a target image (docs/SOLVE.md)."""

from __future__ import annotations

import argparse
import sys

from pipeline.commands.common import add_device_option, add_lights_option
from pipeline.errors import RelightError
from pipeline.progress import progress_bar
from relight_torch import open_cache
from relight_torch.cache.layer import read_cache_layer
from relight_torch.direct.loading import shot_lights
from relight_torch.io.images import read_image
from relight_torch.lights.overrides import write_light_overrides
from relight_torch.solve import FREE_KINDS, DescentSettings, parse_free, solve_lights


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "solve",
        help="solve light settings from a target image",
        description="Find the settings of the shot's lights that make CACHE's relit frame match IMAGE "
        "(linear pixels, the cache's resolution): intensities and colours in closed form (non-negative "
        "least squares of per-light images), position, orientation, size, shaping and colour "
        "temperature by gradient descent through the relighter. Writes a lights layer holding only "
        "the changed attributes, which `relight render CACHE --lights OUT` and `relight reference "
        "SHOT --lights OUT` read.",
    )
    parser.add_argument("cache", metavar="CACHE", help="cache layer written by `relight bake`")
    parser.add_argument("--target", required=True, metavar="IMAGE", help="target image (EXR: linear RGB)")
    parser.add_argument(
        "--mask", metavar="MASK", help="pixel weights (an image of the target's size, grey; default: every pixel 1)"
    )
    add_lights_option(parser)
    parser.add_argument(
        "--solve",
        nargs="+",
        action="extend",
        metavar="PRIM",
        help="light prims to solve (default: every light); the others stay as they are",
    )
    parser.add_argument(
        "--free",
        default="intensity,color",
        metavar="KINDS",
        help=f"comma-separated inputs to solve, of {','.join(FREE_KINDS)} (default: intensity,color)",
    )
    defaults = DescentSettings()
    parser.add_argument(
        "--iterations",
        type=int,
        default=defaults.iterations,
        help=f"evaluations of the loss at most (default {defaults.iterations})",
    )
    parser.add_argument(
        "--regularisation",
        type=float,
        default=defaults.regularisation,
        help=f"weight of the pull toward the starting rig (default {defaults.regularisation:g})",
    )
    parser.add_argument(
        "--robust",
        action="store_true",
        help="fit under Huber's loss: a few pixels the cache cannot resolve (highlights, fireflies) do not "
        "outweigh the frame (targets from another renderer or a camera; not for paint-overs)",
    )
    add_device_option(parser)
    parser.add_argument("-o", "--out", required=True, metavar="SOLVED.usda", help="lights layer to write")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    free = parse_free(args.free)
    if args.iterations < 1 or args.regularisation < 0:
        raise RelightError(
            f"--iterations must be >= 1 and --regularisation >= 0 (got {args.iterations}, {args.regularisation})"
        )
    target = read_image(args.target).pixels
    if target.shape[-1] < 3:
        raise RelightError(f"--target {args.target}: {target.shape[-1]} channel(s), expected RGB")
    mask = read_image(args.mask).pixels[..., 0] if args.mask else None
    relighter = open_cache(args.cache, device=args.device, lights_layer=args.lights)
    settings = DescentSettings(iterations=args.iterations, regularisation=args.regularisation)
    try:
        with progress_bar("solve", settings.iterations, unit="step") as update:
            result = solve_lights(relighter, target, mask, args.solve, free, settings, update, args.robust)
    except RelightError as error:  # name the file a shape or value error is about
        message = str(error)
        for name, path in (("target", args.target), ("mask", args.mask)):
            if message.startswith(f"{name}: "):
                message = f"--{name} {path}: {message[len(name) + 2 :]}"
        raise RelightError(message) from None
    # The layer composes over the shot, not over --lights: its changes are against the shot's own rig.
    write_light_overrides(args.out, shot_lights(read_cache_layer(args.cache)), result.after)
    print(
        f"{args.out}: {len(result.solved)} lights solved ({','.join(free)}), relative error "
        f"{result.loss_start:.4g} -> {result.loss_end:.4g}, {result.iterations} gradient steps, "
        f"{result.seconds:.1f} s"
    )
    for line in result.unresolved:
        print(f"relight: warning: {line}", file=sys.stderr)
    return 0
