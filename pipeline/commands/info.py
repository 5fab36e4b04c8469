"""`relight info`: what the walker sees in a stage, or what a cache layer holds and whether it is usable.

For a stage: counts, lights, cameras, the walker's warnings. For a cache layer (a layer with a
RelightCache prim, whatever its name): provenance (source, camera, content hash, code version,
input files), method and parameters, each payload's size, format and channels, and the verdict —
valid, stale (an input changed since the bake) or corrupt (a payload missing, truncated, replaced
or edited).
"""

from __future__ import annotations

import argparse
import time
import tracemalloc
from collections import Counter
from pathlib import Path

from pipeline.bake.inputs import code_version
from pipeline.commands.common import add_camera_options, add_lights_option
from pipeline.errors import RelightError
from pipeline.scene.load import find_camera, read_scene
from pipeline.scene.types import Scene
from relight_torch.cache.layer import is_cache_layer
from relight_torch.cache.load import load_npy
from relight_torch.cache.status import CacheStatus, PayloadStatus, cache_status
from relight_torch.io.exr import PIXEL_TYPE_NAMES, read_exr_header
from relight_torch.lights.linking import decode_paths
from relight_torch.material_edits import prim_material_paths
from relight_torch.stage import open_stage


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "info",
        help="describe a USD stage as the baker reads it, or check a cache layer",
        description="For a stage: print the triangle, object, material, light and camera counts, with "
        "light types, camera paths and the walker's warnings. For a cache layer written by "
        "`relight bake`: print its provenance, method, parameters and payload files with their "
        "sizes, and whether it is valid, stale or corrupt (exit status 1 unless valid).",
    )
    parser.add_argument("scene", metavar="SCENE", help="USD stage (.usda, .usdc, .usdz) or cache layer (.relight.usda)")
    add_camera_options(parser, required=False)
    add_lights_option(parser)
    parser.set_defaults(run=run)


def _bytes(num_bytes: int) -> str:
    """A size for people: '980 B', '13.0 KiB', '2.5 MiB'."""
    size, unit = float(num_bytes), "B"
    for larger in ("KiB", "MiB", "GiB", "TiB"):
        if size < 1024:
            break
        size, unit = size / 1024, larger
    return f"{num_bytes} B" if unit == "B" else f"{size:.1f} {unit}"


def _exr_lines(status: PayloadStatus) -> list[str]:
    """Channel names grouped by pixel type, raw size, and the constants elided from the file."""
    lines = []
    if status.num_bytes is not None and status.problem is None:
        header = read_exr_header(status.path)
        by_type: dict[str, list[str]] = {}
        for name, dtype in header.channels.items():
            by_type.setdefault(PIXEL_TYPE_NAMES[dtype], []).append(name)
        raw = header.width * header.height * sum(dtype.itemsize for dtype in header.channels.values())
        lines.append(
            f"      {header.width}x{header.height}, {len(header.channels)} channels, "
            f"{header.compression} compression, "
            f"{raw / status.num_bytes:.1f}x smaller than raw ({_bytes(raw)})"
        )
        lines += [f"      {kind}: {' '.join(names)}" for kind, names in sorted(by_type.items())]
    constants = status.payload.constants
    if constants:
        lines.append(
            "      constant (not stored): "
            + ", ".join(f"{name} = {value:g}" for name, value in sorted(constants.items()))
        )
    return lines


def _describe_cache(status: CacheStatus) -> list[str]:
    """Lines describing a checked cache layer."""
    d = status.description
    width, height = d.resolution
    lines = [
        f"{status.path}: relight cache",
        f"  method: {d.method}",
        f"  source: {d.source}",
        f"  camera: {d.camera_path}, {width}x{height}, supersampling {d.supersampling}, "
        f"exposure scale {d.exposure_scale:g}",
        f"  content hash: {d.content_hash}",
        f"  code version: {d.code_version or 'not recorded'}"
        + ("" if not d.code_version or d.code_version == code_version() else f" (this code: {code_version()})"),
        "  parameters: " + (", ".join(f"{k} = {v}" for k, v in sorted(d.parameters.items())) or "none"),
        f"  inputs: {len(d.inputs)}",
    ]
    lines += [f"    {file}  {status.stale_inputs.get(file, 'unchanged')}" for file in sorted(d.inputs)]
    on_disk = sum(p.num_bytes or 0 for p in status.payloads)
    lines.append(f"  payloads: {len(status.payloads)}, {_bytes(on_disk)} on disk")
    for payload_status in status.payloads:
        payload = payload_status.payload
        found = "missing" if payload_status.num_bytes is None else _bytes(payload_status.num_bytes)
        what = (
            f"{payload.dtype}{list(payload.shape)}" if payload.format == "npy" else f"{len(payload.channels)} channels"
        )
        lines.append(
            f"    {payload.name}: {payload.file}, {payload.format}, {found} "
            f"({payload.num_bytes} bytes recorded), {what}, "
            f"{'ok' if payload_status.problem is None else 'BAD'}"
        )
        if payload.format == "exr":
            lines += _exr_lines(payload_status)
    lines += _material_lines(status)
    problems = [p.problem for p in status.payloads if p.problem]
    problems += [f"input {file} {state} since the bake" for file, state in status.stale_inputs.items()]
    lines.append(f"  status: {status.verdict}")
    lines += [f"    {problem}" for problem in problems]
    return lines


def _material_lines(status: CacheStatus) -> list[str]:
    """The material prim paths a cache's materials are edited by (`edit_material`, `relight render
    --materials`), when it stores them and they read back as written."""
    payload = next((p for p in status.payloads if p.payload.name == "materialPaths"), None)
    if payload is None or payload.problem is not None:
        return []
    paths = prim_material_paths(decode_paths(load_npy(status.path, status.description, "materialPaths")))
    return [f"  materials: {len(paths)} (edited by these prim paths)"] + [f"    {path}" for path in paths]


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
    lines.append(
        f"  lights: {len(scene.lights)}"
        + (f" ({', '.join(f'{n} {k}' for k, n in sorted(kinds.items()))})" if kinds else "")
    )
    lines += [f"    {light.path}  {light.kind.value}" for light in scene.lights]
    lines.append(f"  cameras: {len(scene.cameras)}")
    lines += [
        f"    {path}  {camera.width}x{camera.height}, focal length {camera.focal_length:g}, "
        f"aperture {camera.horizontal_aperture:g} x {camera.vertical_aperture:g}"
        for path, camera in sorted(scene.cameras.items())
    ]
    lines.append(f"  warnings: {len(scene.warnings)}")
    lines += [f"    {message}" for message in scene.warnings]
    return lines


def _read(
    path: str | Path, lights_layer: str | Path | None, time: float | None, width: int | None, height: int | None
) -> Scene:
    """The scene of a stage, without `load_scene`'s requirement of geometry."""
    return read_scene(open_stage(path, lights_layer), str(Path(path).resolve()), time=time, width=width, height=height)


def describe_stage(
    path: str | Path,
    *,
    lights_layer: str | Path | None = None,
    time: float | None = None,
    width: int | None = None,
    height: int | None = None,
) -> str:
    """A multi-line description of any stage as the walker reads it (empty stages included).

    Args:
        path: the stage. lights_layer: optional light-edit layer composed over it.
        time: USD time code, None for the first frame. width, height: image size overrides.

    Raises:
        RelightError: the stage or the lights layer cannot be opened.
    """
    return "\n".join(_describe_scene(_read(path, lights_layer, time, width, height)))


def run(args: argparse.Namespace) -> int:
    if is_cache_layer(args.scene):
        given = [
            f"--{name}" for name in ("camera", "lights", "time", "width", "height") if getattr(args, name) is not None
        ]
        if given:
            raise RelightError(f"{args.scene} is a cache layer: stage options ({', '.join(given)}) do not apply")
        status = cache_status(args.scene)
        print("\n".join(_describe_cache(status)))
        return 0 if status.verdict == "valid" else 1
    tracemalloc.start()
    start = time.perf_counter()
    scene = _read(args.scene, args.lights, args.time, args.width, args.height)
    seconds = time.perf_counter() - start
    _, peak_bytes = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    if args.camera is not None:
        find_camera(scene, args.camera)
    print("\n".join(_describe_scene(scene)))
    print(
        f"  import: {seconds:.2f} s, peak {peak_bytes / 2**20:.1f} MiB allocated by Python and numpy "
        f"(tracemalloc; USD's own C++ memory not counted)"
    )
    return 0
