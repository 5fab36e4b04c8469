"""`relight info`: what the walker sees in a stage (counts, lights, cameras, warnings)."""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

from pipeline.commands.common import add_camera_options, add_lights_option
from pipeline.scene.load import find_camera, read_scene
from relight_torch.stage import open_stage
from pipeline.scene.types import Scene


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "info", help="describe a USD stage as the baker reads it",
        description="Print the triangle, object, material, light and camera counts of a stage, "
                    "with light types, camera paths and the walker's warnings.")
    parser.add_argument("scene", metavar="SCENE", help="USD stage (.usda, .usdc, .usdz)")
    add_camera_options(parser, required=False)
    add_lights_option(parser)
    parser.set_defaults(run=run)


def _describe_scene(scene: Scene) -> list[str]:
    """Lines describing a read scene."""
    geometry = scene.geometry
    lines = [
        scene.source,
        f"  up axis {scene.up_axis}, {scene.meters_per_unit:g} m per unit",
        f"  triangles: {geometry.num_triangles}",
        f"  objects: {len(scene.objects)}",
        f"  materials: {len(scene.materials)}",
    ]
    if geometry.num_triangles:
        low, high = scene.bounds
        lines.insert(2, f"  bounds: {low.round(4).tolist()} .. {high.round(4).tolist()}")
    kinds = Counter(light.kind.value for light in scene.lights)
    lines.append(f"  lights: {len(scene.lights)}"
                 + (f" ({', '.join(f'{n} {k}' for k, n in sorted(kinds.items()))})" if kinds else ""))
    lines += [f"    {light.path}  {light.kind.value}" for light in scene.lights]
    lines.append(f"  cameras: {len(scene.cameras)}")
    lines += [f"    {path}  {camera.width}x{camera.height}, focal length {camera.focal_length:g}, "
              f"aperture {camera.horizontal_aperture:g} x {camera.vertical_aperture:g}"
              for path, camera in sorted(scene.cameras.items())]
    lines.append(f"  warnings: {len(scene.warnings)}")
    lines += [f"    {message}" for message in scene.warnings]
    return lines


def _read(path: str | Path, lights_layer: str | Path | None, time: float | None,
          width: int | None, height: int | None) -> Scene:
    """The scene of a stage, without `load_scene`'s requirement of geometry."""
    return read_scene(open_stage(path, lights_layer), str(Path(path).resolve()), time=time,
                      width=width, height=height)


def describe_stage(path: str | Path, *, lights_layer: str | Path | None = None, time: float | None = None,
                   width: int | None = None, height: int | None = None) -> str:
    """A multi-line description of any stage as the walker reads it (empty stages included).

    Args:
        path: the stage. lights_layer: optional light-edit layer composed over it.
        time: USD time code, None for the first frame. width, height: image size overrides.

    Raises:
        RelightError: the stage or the lights layer cannot be opened.
    """
    return "\n".join(_describe_scene(_read(path, lights_layer, time, width, height)))


def run(args: argparse.Namespace) -> int:
    scene = _read(args.scene, args.lights, args.time, args.width, args.height)
    if args.camera is not None:
        find_camera(scene, args.camera)
    print("\n".join(_describe_scene(scene)))
    return 0
