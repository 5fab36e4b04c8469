"""Speed of direct relighting on a deep framebuffer: what each kind of light edit costs.

It bakes a bundled scene, opens the cache with Embree shadows, and times renders after edits
that invalidate different stages of `relight_torch.direct.relighter.Relighter`:

    re-shade, L lights     every light's images dropped, transport (samples, shadow rays,
                           BRDF) kept: what re-running every light shader costs
    rebuild, L lights      everything dropped: samples, Embree shadow rays, BRDF, shading
    move one light         a translation: that light's transport and images
    shaping edit           cone angle and focus of a spot: that light's images
    Barzel cookie edit     the cookie's offset: that light's images
    colour edit            one light's colour: a rescale, nothing shaded
    light-link edit        one light's light link (every object but one, the one cycling):
                           its (N,) mask from the G-buffer's object ids, nothing traced or shaded
                           (a link seen before reuses its mask: with fewer objects than
                           repeats, under one mask pass per edit)

Rigs of 1, 4 and 16 lights are the shot's lights followed by generated sphere, rect and spot
lights (round robin) on a ring above what the camera sees, aimed at its centre. Each row reports
the median and fastest wall time of `repeats` edits (each followed by `render()`, synchronised
on CUDA), the median CPU time of the process (all its threads: on a shared machine the wall
time counts other people's work, this does not), and how many visibility, shading and
light-link mask passes one edit ran.
`format_table` ends with the table of edit kinds a lighting artist makes (colour, shaping,
move, link) and what each recomputes.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import resource
import tempfile
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipeline.bake.direct.bake import bake_direct
from pipeline.benchmarks.stopwatch import Stopwatch
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES
from relight_torch.direct.relighter import Relighter, open_relighter
from relight_torch.direct.settings import RelightSettings
from relight_torch.io.atomic import write_text_atomic
from relight_torch.lights.light import BarzelShaping, Light, LightKind, Shaping
from relight_torch.metrics import psnr

RIG_SIZES = (1, 4, 16)
# The rig the single-light edits are timed on.
EDIT_RIG_SIZE = 4
# Generated lights: sizes and ring placement as fractions of the diagonal of what the camera sees.
SPHERE_RADIUS = 0.01
RECT_SIDE = 0.03
SPOT_RADIUS = 0.005
RING_RADIUS = 0.4
RING_HEIGHT = 0.35
MOVE_STEP = 0.01
# Illuminance each generated light brings to the centre, as a fraction of 1 / (rig size).
TARGET_ILLUMINANCE = 0.5


@dataclass(frozen=True)
class Row:
    """One timed case.

    Attributes:
        case: what was edited (see the module doc).
        num_lights: lights in the rig.
        median_ms, min_ms: wall time of one edit and render.
        cpu_ms: median CPU time of the process (every thread) for one edit and render.
        visibility_passes, shading_passes, mask_passes: passes one edit ran (the relighter's counters).
    """

    case: str
    num_lights: int
    median_ms: float
    min_ms: float
    cpu_ms: float
    visibility_passes: float
    shading_passes: float
    mask_passes: float


@dataclass(frozen=True)
class Report:
    """Rows plus what they were measured on.

    Attributes:
        rows: the timed cases.
        context: (name, value) lines: scene, resolution, device, threads, sampling, sizes, memory.
    """

    rows: tuple[Row, ...]
    context: tuple[tuple[str, str], ...]


def look_at(position: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(4, 4) float64 world_from_light placing a light at `position` with its -Z axis towards `target`."""
    z_axis = position - target
    z_axis = z_axis / np.linalg.norm(z_axis)
    x_axis = np.cross(up, z_axis)
    if np.linalg.norm(x_axis) < 1e-6:  # looking along `up`: any perpendicular axis will do
        x_axis = np.cross(np.roll(up, 1), z_axis)
    x_axis = x_axis / np.linalg.norm(x_axis)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = x_axis, np.cross(z_axis, x_axis), z_axis, position
    return matrix


def generated_light(index: int, num_lights: int, centre: np.ndarray, diagonal: float, up: np.ndarray) -> Light:
    """The index-th generated light: sphere, rect or spot by index mod 3, on a ring above `centre`.

    Normalized, with an intensity giving about TARGET_ILLUMINANCE / num_lights at the centre.
    """
    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 0.0, 1.0])
    side = side / np.linalg.norm(side)
    other = np.cross(up, side)
    azimuth = 2.399963 * index  # golden angle: well spread for any count
    position = centre + diagonal * (
        RING_RADIUS * (math.cos(azimuth) * side + math.sin(azimuth) * other) + RING_HEIGHT * up
    )
    world_from_light = look_at(position, centre, up)
    distance2 = float(np.sum((position - centre) ** 2))
    illuminance = TARGET_ILLUMINANCE / num_lights
    path = f"/Bench/Light{index}"
    kind = index % 3
    if kind == 0:
        return Light(
            path,
            LightKind.SPHERE,
            world_from_light,
            intensity=4.0 * distance2 * illuminance,
            normalize=True,
            radius=SPHERE_RADIUS * diagonal,
        )
    if kind == 1:
        return Light(
            path,
            LightKind.RECT,
            world_from_light,
            intensity=distance2 * illuminance,
            normalize=True,
            width=RECT_SIDE * diagonal,
            height=RECT_SIDE * diagonal,
        )
    return Light(
        path,
        LightKind.SPHERE,
        world_from_light,
        intensity=8.0 * distance2 * illuminance,
        normalize=True,
        radius=SPOT_RADIUS * diagonal,
        shaping=Shaping(focus=2.0, cone_angle=30.0, cone_softness=0.2),
    )


def bench_rig(
    shot_lights: list[Light], num_lights: int, centre: np.ndarray, diagonal: float, up: np.ndarray
) -> list[Light]:
    """The shot's first lights, then generated ones, `num_lights` in all."""
    rig = list(shot_lights[:num_lights])
    rig += [generated_light(i, num_lights, centre, diagonal, up) for i in range(len(rig), num_lights)]
    return rig


PASSES = ("visibility", "shading", "masks")
# The edit kinds of the lighting-artist table: kind -> the row that times it.
EDIT_KINDS = {
    "colour": "colour edit",
    "shaping": "shaping edit (cone, focus)",
    "move": "move one light (Embree)",
    "link": "light-link edit (masks)",
}


def time_edits(
    relighter: Relighter, edit: Callable[[int], None], repeats: int
) -> tuple[list[float], list[float], float, float, float]:
    """Wall and process CPU times (ms) of `repeats` calls of edit(k) + render, after one untimed
    warm-up call.

    Returns:
        (wall times, CPU times, then visibility, shading and mask passes per edit).
    """
    sync = torch.cuda.synchronize if relighter.gbuffer.device.type == "cuda" else (lambda: None)
    edit(-1)
    relighter.render()
    sync()
    before = dict(relighter.counters)
    watch = Stopwatch()
    for k in range(repeats):
        with watch.section():
            edit(k)
            relighter.render()
            sync()
    passes = [(relighter.counters[name] - before.get(name, 0)) / repeats for name in PASSES]
    return [1e3 * t for t in watch.wall], [1e3 * t for t in watch.cpu], *passes


def _row(case: str, relighter: Relighter, edit: Callable[[int], None], repeats: int) -> Row:
    times, cpu_times, *passes = time_edits(relighter, edit, repeats)
    return Row(
        case, len(relighter.lights), float(np.median(times)), float(np.min(times)), float(np.median(cpu_times)), *passes
    )


def _replacer(relighter: Relighter, light: Light, change: Callable[[Light, int], Light]) -> Callable[[int], None]:
    """edit(k): set `change(light, k)`; even and odd k alternate between two states."""
    return lambda k: relighter.set_light(change(light, k % 2))


def _moved(light: Light, step: float) -> Callable[[Light, int], Light]:
    def change(original: Light, parity: int) -> Light:
        matrix = original.world_from_light.copy()
        matrix[0, 3] += step * (1 - 2 * parity)
        return dataclasses.replace(original, world_from_light=matrix)

    return change


def _reshaped(original: Light, parity: int) -> Light:
    shaping = original.shaping or Shaping()
    return dataclasses.replace(
        original,
        shaping=dataclasses.replace(
            shaping, cone_angle=shaping.cone_angle * (0.9 if parity else 1.1), focus=shaping.focus + 0.5 * parity
        ),
    )


def _cookie_moved(cookie: np.ndarray) -> Callable[[Light, int], Light]:
    def change(original: Light, parity: int) -> Light:
        return dataclasses.replace(
            original, barzel=BarzelShaping(cookie=cookie, cookie_scale=(0.5, 0.5), cookie_offset=(0.05 * parity, 0.0))
        )

    return change


def _recoloured(original: Light, parity: int) -> Light:
    return dataclasses.replace(original, color=(1.0, 0.8, 0.6) if parity else (0.6, 0.8, 1.0))


def _relinked(relighter: Relighter, light: Light) -> Callable[[int], None]:
    """edit(k): link `light` to every object of the cache but object k (mod their number)."""
    paths = relighter.object_paths

    def edit(k: int) -> None:
        skipped = k % len(paths)
        relighter.set_light(
            dataclasses.replace(light, light_link=tuple(p for i, p in enumerate(paths) if i != skipped))
        )

    return edit


def checker_cookie(size: int = 64, cells: int = 8) -> np.ndarray:
    """(size, size, 3) float32 checkerboard of 1 and 0.2: a gobo."""
    index = np.arange(size) * cells // size
    board = np.where((index[:, None] + index[None, :]) % 2 == 0, 1.0, 0.2).astype(np.float32)
    return np.repeat(board[..., None], 3, axis=-1)


def run_benchmark(
    scene_name: str = "glossy",
    width: int = 640,
    height: int = 480,
    supersampling: int = 1,
    device: str = "cpu",
    repeats: int = 9,
    settings: RelightSettings = RelightSettings(),
    accuracy: bool = False,
    work_dir: Path | None = None,
) -> Report:
    """Bake `scene_name` and time every case of the module doc.

    Args:
        scene_name: a key of `pipeline.scenes.SCENES`.
        width, height: image size in pixels; supersampling: sub-samples per pixel side.
        device: torch device of the relighting kernels (visibility stays on Embree, CPU).
        repeats: timed edits per row.
        settings: the relighter's sampling.
        accuracy: also render the edit rig with every light at `settings.area_samples` and report
            the PSNR of the benchmarked image against it (slow: full sampling).
        work_dir: where the scene and its cache are written (a temporary directory if None).
    """
    with tempfile.TemporaryDirectory(prefix="bench-direct-") as temp:
        directory = Path(work_dir or temp)
        tracemalloc.start()
        layer, up = _bake(scene_name, directory, width, height, supersampling)
        relighter = open_relighter(layer, device=device, settings=settings)
        relighter.render()
        _, numpy_peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        cache_bytes = sum(path.stat().st_size for path in layer.parent.iterdir() if path.is_file())
        rows, rig_bytes = _timed_rows(relighter, up, repeats)
        context = [
            (
                "scene",
                f"{scene_name}, {width}x{height}, supersampling {supersampling}, "
                f"{relighter.gbuffer.num_samples} shading points",
            ),
            ("device", _device_name(device)),
            (
                "settings",
                f"area_samples {settings.area_samples}, full_sampling_angle "
                f"{settings.full_sampling_angle} deg, min_area_samples {settings.min_area_samples}",
            ),
            (
                "samples per light (edit rig)",
                ", ".join(str(relighter.num_light_samples(light)) for light in relighter.lights),
            ),
            ("bake cache on disk", f"{cache_bytes} bytes"),
            ("relighter caches, 16-light rig", f"{rig_bytes} bytes"),
            ("peak numpy memory (bake + open + first render)", f"{numpy_peak} bytes"),
            ("peak resident memory", f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024} bytes"),
        ]
        if device.startswith("cuda"):
            context.append(("peak CUDA memory", f"{torch.cuda.max_memory_allocated()} bytes"))
        if accuracy:
            context.append(
                ("PSNR vs full sampling (edit rig)", f"{_accuracy(layer, relighter, device, settings):.2f} dB")
            )
    return Report(tuple(rows), tuple(context))


def _bake(scene_name: str, directory: Path, width: int, height: int, supersampling: int) -> tuple[Path, np.ndarray]:
    """(cache layer, (3,) unit up vector of the stage)."""
    bundled = SCENES[scene_name]
    scene = load_scene(bundled.write(directory / "scene"), width=width, height=height)
    layer = bake_direct(scene, find_camera(scene, bundled.camera), directory / "cache", scene_name, supersampling)
    return layer, np.array([0.0, 0.0, 1.0]) if scene.up_axis == "Z" else np.array([0.0, 1.0, 0.0])


def _timed_rows(relighter: Relighter, up: np.ndarray, repeats: int) -> tuple[list[Row], int]:
    """Every row of the table, and the relighter's cache bytes with the largest rig."""
    shot = relighter.lights
    positions = relighter.gbuffer.position.detach().cpu().numpy().astype(np.float64)
    low, high = positions.min(axis=0), positions.max(axis=0)
    centre, diagonal = 0.5 * (low + high), float(np.linalg.norm(high - low))
    rows, rig_bytes = [], 0
    for num_lights in RIG_SIZES:
        relighter.set_lights(bench_rig(shot, num_lights, centre, diagonal, up))
        rows.append(_row("re-shade", relighter, lambda k: relighter.invalidate(), repeats))
        rig_bytes = relighter.cache_bytes()
    relighter.set_lights(bench_rig(shot, EDIT_RIG_SIZE, centre, diagonal, up))
    rows.append(
        _row("rebuild (visibility + shading)", relighter, lambda k: relighter.invalidate(visibility=True), repeats)
    )
    lights = relighter.lights
    spot = next((light for light in lights if light.shaping is not None), lights[-1])
    edits = (
        ("move one light (Embree)", lights[0], _moved(lights[0], MOVE_STEP * diagonal)),
        ("shaping edit (cone, focus)", spot, _reshaped),
        ("Barzel cookie edit", spot, _cookie_moved(checker_cookie())),
        ("colour edit", lights[0], _recoloured),
    )
    for case, light, change in edits:
        rows.append(_row(case, relighter, _replacer(relighter, light, change), repeats))
        relighter.set_light(light)
    if relighter.object_paths:
        rows.append(_row("light-link edit (masks)", relighter, _relinked(relighter, lights[0]), repeats))
        relighter.set_light(lights[0])
    return rows, rig_bytes


def _accuracy(layer: Path, relighter: Relighter, device: str, settings: RelightSettings) -> float:
    reference = open_relighter(layer, device=device, settings=dataclasses.replace(settings, full_sampling_angle=0.0))
    reference.set_lights(relighter.lights)
    return psnr(relighter.render().cpu().numpy(), reference.render().cpu().numpy())


def _device_name(device: str) -> str:
    if device.startswith("cuda"):
        return f"{device} ({torch.cuda.get_device_name(torch.device(device))})"
    return f"cpu, {torch.get_num_threads()} torch threads"


def _aligned(cells: list[tuple[str, ...]]) -> list[str]:
    """Rows of cells as aligned lines (first column left, the others right), a rule under the header."""
    widths = [max(len(row[i]) for row in cells) for i in range(len(cells[0]))]
    lines = [
        "  ".join(
            cell.ljust(w) if i == 0 else cell.rjust(w) for i, (cell, w) in enumerate(zip(row, widths, strict=True))
        )
        for row in cells
    ]
    lines.insert(1, "-" * len(lines[0]))
    return lines


def edit_kind_rows(report: Report) -> list[tuple[str, Row]]:
    """(kind, row) for each edit kind of `EDIT_KINDS` the report timed, in that order."""
    by_case = {row.case: row for row in report.rows}
    return [(kind, by_case[case]) for kind, case in EDIT_KINDS.items() if case in by_case]


def _recomputed(row: Row) -> str:
    passes = {"visibility": row.visibility_passes, "shading": row.shading_passes, "masks": row.mask_passes}
    done = [f"{name} x{count:.3g}" for name, count in passes.items() if count]
    return ", ".join(done) or "nothing (a rescale)"


def format_table(report: Report) -> str:
    """The rows as an aligned text table, the context lines, then the table of edit kinds."""
    header = ("case", "lights", "median ms", "min ms", "cpu ms", "visibility", "shading", "masks")
    cells = [header] + [
        (
            r.case,
            str(r.num_lights),
            f"{r.median_ms:.2f}",
            f"{r.min_ms:.2f}",
            f"{r.cpu_ms:.2f}",
            f"{r.visibility_passes:.3g}",
            f"{r.shading_passes:.3g}",
            f"{r.mask_passes:.3g}",
        )
        for r in report.rows
    ]
    lines = _aligned(cells) + [f"{name}: {value}" for name, value in report.context]
    kinds = edit_kind_rows(report)
    if kinds:
        lines += ["", f"edit kinds (one light of the {kinds[0][1].num_lights}-light rig):"]
        lines += _aligned(
            [("edit", "median ms", "min ms", "cpu ms", "recomputed")]
            + [
                (kind, f"{row.median_ms:.2f}", f"{row.min_ms:.2f}", f"{row.cpu_ms:.2f}", _recomputed(row))
                for kind, row in kinds
            ]
        )
    return "\n".join(lines)


def write_csv(report: Report, path: str | Path) -> None:
    """The rows as CSV (one column per Row field), the context as trailing '# name: value' lines."""
    buffer = io.StringIO(newline="")
    writer = csv.writer(buffer)
    fields = [f.name for f in dataclasses.fields(Row)]
    writer.writerow(fields)
    for row in report.rows:
        writer.writerow([getattr(row, name) for name in fields])
    for name, value in report.context:
        buffer.write(f"# {name}: {value}\n")
    write_text_atomic(path, buffer.getvalue())
