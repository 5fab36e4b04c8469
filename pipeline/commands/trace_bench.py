"""`relight trace-bench`: rays per second of our tracing layer against raw embreex.

Standalone by default (a synthetic displaced heightfield seen by a pinhole camera); with
`--scene SHOT.usd --camera PRIM` it traces the shot's geometry through that camera instead.
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from pipeline import tracing_bench
from pipeline.commands.common import add_camera_options
from pipeline.errors import RelightError
from pipeline.scene.types import Geometry


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "trace-bench",
        help="benchmark the ray tracer against raw embreex",
        description="Time closest-hit and occlusion queries of pipeline.tracing.Tracer against "
        "raw embreex calls on the same rays, and print rays/s and their ratio.",
    )
    parser.add_argument(
        "--triangles",
        type=int,
        default=200_000,
        metavar="N",
        help="triangles of the synthetic heightfield (default: 200000)",
    )
    parser.add_argument(
        "--rays",
        type=int,
        default=1_000_000,
        metavar="N",
        help="camera rays per call (default: 1000000); --width/--height override it",
    )
    parser.add_argument(
        "--repeats", type=int, default=5, metavar="K", help="timed runs per row, the median is reported (default: 5)"
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        metavar="K",
        help="threads of the multi-threaded rows (default: all usable CPUs)",
    )
    parser.add_argument(
        "--scene", metavar="PATH", help="trace this USD stage instead of the synthetic heightfield (needs --camera)"
    )
    add_camera_options(parser, required=False)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    for option in ("triangles", "rays", "repeats", "threads", "width", "height"):
        value = getattr(args, option)
        if value is not None and value < 1:
            raise RelightError(f"--{option} must be at least 1, got {value}")
    if args.scene is None:
        if args.camera is not None:
            raise RelightError("--camera needs --scene (the synthetic scene has its own camera)")
        geometry = tracing_bench.heightfield_geometry(args.triangles)
        origins, directions = tracing_bench.synthetic_rays(args.rays)
        source = f"synthetic heightfield, {args.triangles} triangles requested"
    else:
        geometry, origins, directions = _scene_rays(args)
        source = f"{args.scene} through {args.camera}"
    print(f"scene: {source}; {geometry.num_triangles} triangles, {len(origins)} camera rays")
    timings = tracing_bench.run_benchmark(geometry, origins, directions, repeats=args.repeats, num_threads=args.threads)
    print(tracing_bench.format_table(timings))
    return 0


def _scene_rays(args: argparse.Namespace) -> tuple[Geometry, np.ndarray, np.ndarray]:
    """Geometry and (N, 3) float32 camera rays of `--scene` through `--camera`.

    The image keeps the camera's aspect ratio with about `--rays` pixels, unless --width and
    --height are given.
    """
    # Imported here so that the synthetic benchmark does not depend on the USD walker.
    from pipeline.scene import load_scene
    from pipeline.scene.camera import camera_rays

    if args.camera is None:
        raise RelightError("--scene needs --camera PRIM")
    scene = load_scene(args.scene, time=args.time, width=args.width, height=args.height)
    if args.camera not in scene.cameras:
        raise RelightError(
            f"--camera {args.camera}: no such camera in {args.scene} "
            f"(cameras: {', '.join(sorted(scene.cameras)) or 'none'})"
        )
    camera = scene.cameras[args.camera]
    if args.width is None or args.height is None:
        aspect = camera.width / camera.height
        height = max(1, round(np.sqrt(args.rays / aspect)))
        camera = dataclasses.replace(camera, width=max(1, round(height * aspect)), height=height)
    origins, directions = camera_rays(camera)
    return scene.geometry, origins.reshape(-1, 3), directions.reshape(-1, 3)
