"""`relight render`: relight a baked cache under the shot's lights and a layer of edits."""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch

from pipeline.bake.methods import bake_method, bake_methods
from pipeline.commands.common import (
    add_device_option,
    add_lights_option,
    add_materials_option,
    add_memory_budget_option,
    relight_settings,
)
from pipeline.errors import RelightError
from relight_torch import open_cache
from relight_torch.cache.layer import read_cache_layer
from relight_torch.io.exr import exr_layer_names, write_rgb_exr
from relight_torch.io.preview import write_png
from relight_torch.material_edits import apply_materials_layer
from relight_torch.progressive import DEFAULT_BUDGET_MS, check_progressive, progressive_frames


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "render",
        help="relight a baked cache",
        description="Relight CACHE (a <stem>.relight.usda) with the shot's lights, with LAYER's light "
        "edits composed over them, and write a linear float EXR (R, G, B). With --aov lightgroups "
        "the EXR also holds one layer <group>.R/G/B per light group (relight:lightGroup, default "
        "the light's name; <group>_direct and <group>_indirect for methods with indirect light) "
        "and an 'emission' layer when surfaces emit; the layers sum to R, G, B.",
    )
    parser.add_argument("cache", metavar="CACHE", help="cache layer written by `relight bake`")
    add_lights_option(parser)
    add_materials_option(parser, " (direct and cuts caches)")
    add_device_option(parser)
    parser.add_argument("-o", "--out", required=True, metavar="OUT.exr", help="output EXR")
    parser.add_argument("--png", metavar="OUT.png", help="also write an 8-bit sRGB preview")
    parser.add_argument(
        "--shadows",
        default="embree",
        choices=("embree", "shadowmaps"),
        help="exact Embree shadow rays (CPU) or torch shadow maps (default: embree)",
    )
    add_memory_budget_option(parser)
    parser.add_argument(
        "--aov",
        action="append",
        default=[],
        choices=("lightgroups",),
        help="extra EXR layers: 'lightgroups' (one per light group)",
    )
    progressive = parser.add_argument_group("progressive refinement (direct and transfer caches, the shot cache)")
    progressive.add_argument(
        "--progressive",
        action="store_true",
        help="render coarse frames first (one point per 16x16 down to 1x1 pixels, upsampled edge-aware), then "
        "the exact frame written to OUT; logs each frame's milliseconds",
    )
    progressive.add_argument(
        "--budget-ms",
        type=float,
        default=DEFAULT_BUDGET_MS,
        metavar="MS",
        help=f"time budget of the first frame (default {DEFAULT_BUDGET_MS:g})",
    )
    progressive.add_argument("--frames", metavar="DIR", help="also write each progressive frame as DIR/frame-NN.exr")
    moving = ", ".join(name for name, method in bake_methods().items() if method.render_views is not None)
    view = parser.add_argument_group(f"moving camera ({moving} caches)")
    view.add_argument(
        "--camera",
        metavar="PRIM",
        help="render from this camera prim, in the shot or in the --lights layer (default: the cache's camera)",
    )
    view.add_argument(
        "--time",
        type=float,
        nargs="+",
        action="extend",
        metavar="T",
        help="time codes to read the camera at, one frame each: a camera path "
        "(--time 1 2 3, or --time repeated; OUT gets .<T> per frame)",
    )
    view.add_argument("--width", type=int, metavar="W", help="image width (default: the cache's)")
    view.add_argument("--height", type=int, metavar="H", help="image height (default: the cache's)")
    view.add_argument(
        "--fill-holes", action="store_true", help="bake the surfaces no caching camera saw, on demand (loads the shot)"
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    method = bake_method(read_cache_layer(args.cache).method)
    if args.progressive and method.render_views is not None:
        raise RelightError(
            f"--progressive: {args.cache} is a {method.name!r} cache, whose relighter has no progressive refinement"
        )
    if args.budget_ms < 0:
        raise RelightError(f"--budget-ms must be >= 0, got {args.budget_ms}")
    if method.render_views is not None:
        return run_views(args, start, method.render_views)
    if args.camera:
        moving = " or ".join(f"--method {name}" for name, other in bake_methods().items() if other.render_views)
        raise RelightError(
            f"--camera: {args.cache} is a {method.name!r} cache, baked for its camera only; bake it "
            f"with {moving} to move the camera"
        )
    relighter = open_cache(
        args.cache, device=args.device, shadows=args.shadows, lights_layer=args.lights, settings=relight_settings(args)
    )
    if args.materials:
        try:
            apply_materials_layer(relighter, read_cache_layer(args.cache), args.materials)
        except RelightError as error:
            raise RelightError(f"--materials: {args.cache}: {error}") from None
    if args.progressive:
        try:
            check_progressive(relighter)
        except RelightError as error:
            raise RelightError(f"--progressive: {args.cache} ({method.name!r} cache): {error}") from None
        image = render_progressive(relighter, args.budget_ms, args.frames).cpu().numpy()
    else:
        image = relighter.render().cpu().numpy()
    write_rgb_exr(args.out, image, light_group_layers(relighter) if "lightgroups" in args.aov else None)
    if args.png:
        write_png(args.png, image)
    print(
        f"{args.out}: {image.shape[1]}x{image.shape[0]}, {len(relighter.lights)} lights, "
        f"{time.perf_counter() - start:.2f} s including load"
    )
    return 0


def render_progressive(relighter, budget_ms: float, frames_dir: str | None) -> torch.Tensor:
    """The exact frame of `relighter` after its coarse frames (`relight_torch.progressive`), each
    logged (level, ms) and, with `frames_dir`, written as frame-NN.exr there."""
    if frames_dir is not None:
        os.makedirs(frames_dir, exist_ok=True)
    image = None
    for number, frame in enumerate(progressive_frames(relighter, budget_ms)):
        level = "exact" if frame.stride is None else f"1 point per {frame.stride}x{frame.stride} pixels"
        print(
            f"frame {number}: {level}, {frame.frame_ms:.1f} ms ({frame.elapsed_ms:.1f} ms since the start), "
            f"{frame.evaluated} light evaluations"
        )
        if frames_dir is not None:
            write_rgb_exr(os.path.join(frames_dir, f"frame-{number:02d}.exr"), frame.image.cpu().numpy())
        image = frame.image
    assert image is not None, "progressive_frames yields at least the exact frame"
    return image


def run_views(args: argparse.Namespace, start: float, render_views) -> int:
    """`relight render` of a cache whose relighter needs a view: its method's `render_views` writes
    one frame per --time from --camera (or the cache's camera)."""
    relighter = open_cache(
        args.cache, device=args.device, shadows=args.shadows, lights_layer=args.lights, settings=relight_settings(args)
    )
    render_views(relighter, args, light_group_layers if "lightgroups" in args.aov else None)
    print(f"{time.perf_counter() - start:.2f} s including load")
    return 0


def light_group_layers(relighter) -> dict[str, np.ndarray]:
    """EXR layer -> (H, W, 3) image of each light group (`CacheRelighter.light_group_images`), plus
    'emission' where surfaces emit."""
    images = {name: image.cpu().numpy() for name, image in relighter.light_group_images().items()}
    emission = relighter.emission_image().cpu().numpy()
    if emission.any():
        images = {"emission": emission} | images
    return dict(zip(exr_layer_names(list(images)), images.values(), strict=True))
