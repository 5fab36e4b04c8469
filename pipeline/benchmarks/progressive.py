"""Progressive relighting after each edit kind: the first frame's time and quality, and the convergence.

    python -m pipeline.benchmarks.progressive [--width 640 --height 480] [--repeats 7] [--budget-ms 33] \
        [--reference-size 160 120 --spp 256] --out docs/bench/progressive [--work DIR]

On the Cornell box: the shot cache (the default bake's choice, made by `bake_shot` at --shot-size, then
its sizes baked at --width x --height, as `shot_accuracy --timing-size` does) and the direct method
(supersampling 2). Per edit kind and cache, each repetition sets the rig before the edit, renders it
exactly (untimed: the relighter is warm, as in a session), makes the edit and runs
`progressive_frames` with the budget to the exact frame, one cost model per relighter carried across
repetitions; a first repetition per edit kind is not counted (it builds the coarse levels' weights).
Reported: median ms of the first frame and its level, median PSNR of the first frame against the
converged one, the converged frame's difference from a fresh relighter's `render()`, median ms to
the converged frame, and PSNR of both frames against the path tracer's full frame (`relight
reference`) at --reference-size, the relit frames box-filtered to it. Edit kinds a cache's relighter
lacks the capability for (`unsupported`: material edits, a camera move) are listed as such; the
light edits are the ones measured here (`pipeline.benchmarks.first_frame` times the others' first
frame). Writes progressive.csv and summary.md into --out.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from pipeline.bake.direct.bake import bake_direct
from pipeline.bake.methods import bake_method
from pipeline.bake.shot import DEFAULT_TARGET_DB, bake_shot
from pipeline.benchmarks import run_in_work
from pipeline.benchmarks.bench.measure import machine_description, moved
from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES
from pipeline.scenes.lights import NEW_LIGHT_PATH, new_sphere_layer
from relight_torch import open_cache
from relight_torch.cache.layer import read_cache_layer
from relight_torch.direct.images import box_filter
from relight_torch.direct.loading import shot_lights
from relight_torch.io.atomic import write_text_atomic
from relight_torch.lights.light import Light, LightKind, Shaping
from relight_torch.methods import relight_method
from relight_torch.metrics import psnr
from relight_torch.progressive import CostModel, level_label, progressive_frames
from relight_torch.protocol import CacheRelighter

SCENE = "cornell_box"
LIGHT_EDITS = ("colour", "shaping", "move", "new light", "dome turn")
MATERIAL_EDITS = ("material colour", "material roughness")
CAMERA_EDITS = ("camera move",)
EDITS = (*LIGHT_EDITS, *MATERIAL_EDITS, *CAMERA_EDITS)
FIELDS = (
    "cache",
    "method",
    "edit",
    "repeats",
    "first_level",
    "first_ms",
    "first_cpu_ms",
    "first_psnr_vs_converged_db",
    "converged_ms",
    "converged_max_diff",
    "first_psnr_vs_reference_db",
    "converged_psnr_vs_reference_db",
    "level_ms",
    "level_psnr_db",
    "note",
)

Rig = list[Light]


def _sky() -> np.ndarray:
    """The bench dome's image: a warm sun patch on a dim blue sky."""
    texture = np.empty((32, 64, 3), np.float32)
    texture[:] = (0.02, 0.03, 0.05)
    texture[8:12, 20:26] = (6.0, 5.0, 4.0)
    return texture


_SKY = _sky()


def dome(turn_degrees: float) -> Light:
    """A textured dome (`_sky`), turned about +Y by `turn_degrees`. Every turn shares one image
    array, as a session turning a dome does (`dataclasses.replace` of its transform): the relighter
    keeps what it derives from an image (its sampler, its irradiance table) per array."""
    texture = _SKY
    angle = math.radians(turn_degrees)
    world_from_light = np.eye(4)
    world_from_light[[0, 0, 2, 2], [0, 2, 0, 2]] = (math.cos(angle), math.sin(angle), -math.sin(angle), math.cos(angle))
    return Light("/World/BenchDome", LightKind.DOME, world_from_light, intensity=1.0, texture=texture)


def edit_rigs(lights: Rig, new_light: Light) -> dict[str, Callable[[int], tuple[Rig, Rig]]]:
    """Edit kind -> k -> (rig before the edit, rig after it), different for each repetition k."""
    first, rest = lights[0], lights[1:]
    shaping = first.shaping or Shaping()

    def shaped(focus: float) -> Light:
        return dataclasses.replace(first, shaping=dataclasses.replace(shaping, focus=focus))

    def added(k: int) -> Light:
        return moved(new_light, 0.002 * k)

    return {
        "colour": lambda k: (
            [dataclasses.replace(first, color=(1.0, 0.9, 0.8 - 0.01 * k)), *rest],
            [dataclasses.replace(first, color=(1.0, 0.7, 0.5 - 0.01 * k)), *rest],
        ),
        "shaping": lambda k: ([shaped(1.0 + 0.1 * k), *rest], [shaped(3.0 + 0.1 * k), *rest]),
        "move": lambda k: ([moved(first, 0.01 * k), *rest], [moved(first, 0.01 * (k + 1)), *rest]),
        "new light": lambda k: (lights, [*lights, added(k)]),
        "dome turn": lambda k: ([*lights, dome(10.0 * k)], [*lights, dome(10.0 * k + 30.0)]),
    }


def unsupported(relighter: CacheRelighter, method: str, edit: str) -> str | None:
    """Why `relighter` (of cache method `method`) cannot make an edit kind, from what it declares
    (None: it can): a material edit needs `material_edits`, a camera move its method's
    `needs_view` (`relight_torch.methods`); every relighter takes light edits."""
    if edit in MATERIAL_EDITS and not relighter.material_edits:
        return "material_edits is False"
    if edit in CAMERA_EDITS and not relight_method(method).needs_view:
        return "renders its baked camera only (needs_view is False)"
    return None


def reference_image(scene, camera, rig: Rig, spp: int) -> np.ndarray:
    """The path tracer's full frame (H, W, 3) of `scene` under `rig`."""
    lit = dataclasses.replace(scene, lights=rig)
    return PathTracer(lit, ReferenceSettings(spp=spp)).render(camera).mean


def downsampled(image: torch.Tensor, size: tuple[int, int]) -> np.ndarray:
    """An (H, W, 3) frame box-filtered to (W', H') = `size` (H and W multiples of them)."""
    factor = image.shape[1] // size[0]
    return box_filter(image, factor).cpu().numpy() if factor > 1 else image.cpu().numpy()


def measure(
    layer: Path, label: str, rigs: dict[str, Callable[[int], tuple[Rig, Rig]]], args, references: dict[str, np.ndarray]
) -> list[dict[str, object]]:
    """The rows of one cache: every edit kind, `args.repeats` timed repetitions after one untimed."""
    relighter = open_cache(layer)
    fresh = open_cache(layer)
    method = read_cache_layer(layer).method
    costs = CostModel()
    rows: list[dict[str, object]] = []
    for edit in args.edits:
        row: dict[str, object] = {"cache": label, "method": method, "edit": edit, "repeats": 0}
        reason = unsupported(relighter, method, edit)
        if reason is not None or edit not in rigs:
            row["note"] = f"not supported: {reason}" if reason else "not measured here: see first_frame.md"
            rows.append(row)
            continue
        first_ms, first_cpu_ms, first_psnr, converged_ms, levels, level_psnr, first_level = [], [], [], [], {}, {}, []
        for k in range(args.repeats + 1):
            before, after = rigs[edit](k)
            relighter.set_lights(before)
            relighter.render()
            relighter.set_lights(after)
            cpu = time.process_time()
            sequence = progressive_frames(relighter, args.budget_ms, costs=costs)
            frames = [next(sequence)]
            cpu = time.process_time() - cpu
            frames += list(sequence)
            if k == 0:
                fresh.set_lights(after)
                row["converged_max_diff"] = float((frames[-1].image - fresh.render()).abs().max())
                reference = references[edit]
                size = (reference.shape[1], reference.shape[0])
                row["first_psnr_vs_reference_db"] = psnr(downsampled(frames[0].image, size), reference)
                row["converged_psnr_vs_reference_db"] = psnr(downsampled(frames[-1].image, size), reference)
                continue  # the warm-up: level weights built, costs learnt
            first_ms.append(frames[0].frame_ms)
            first_cpu_ms.append(1e3 * cpu)
            first_level.append(level_label(frames[0].stride))
            first_psnr.append(psnr(frames[0].image.cpu().numpy(), frames[-1].image.cpu().numpy()))
            converged_ms.append(frames[-1].elapsed_ms)
            converged = frames[-1].image.cpu().numpy()
            for frame in frames:
                name = "exact" if frame.stride is None else str(frame.stride)
                levels.setdefault(name, []).append(frame.frame_ms)
                if frame.stride is not None:
                    level_psnr.setdefault(name, []).append(psnr(frame.image.cpu().numpy(), converged))
        row.update(
            repeats=args.repeats,
            first_level=statistics.mode(first_level),
            first_ms=statistics.median(first_ms),
            first_cpu_ms=statistics.median(first_cpu_ms),
            first_psnr_vs_converged_db=statistics.median(first_psnr),
            converged_ms=statistics.median(converged_ms),
            level_ms=" ".join(f"{name}:{statistics.median(ms):.0f}" for name, ms in levels.items()),
            level_psnr_db=" ".join(f"{name}:{statistics.median(db):.1f}" for name, db in level_psnr.items()),
            note="",
        )
        rows.append(row)
        print(row, flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--shot-size", type=int, nargs=2, default=(160, 120), metavar=("W", "H"))
    parser.add_argument("--quality", type=float, default=DEFAULT_TARGET_DB)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--budget-ms", type=float, default=33.0)
    parser.add_argument("--reference-size", type=int, nargs=2, default=(160, 120), metavar=("W", "H"))
    parser.add_argument("--spp", type=int, default=256)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--work", type=Path, help="bakes and references kept between runs (default: temporary)")
    parser.add_argument(
        "--shot-cache",
        type=Path,
        help="a shot cache of the Cornell box at --width x --height to use instead of choosing and baking one "
        "(e.g. `relight bake --method transfer` at the sizes docs/bench/shot records)",
    )
    parser.add_argument("--direct-cache", type=Path, help="a direct cache to use instead of baking one")
    parser.add_argument(
        "--edits",
        nargs="+",
        choices=EDITS,
        default=list(EDITS),
        metavar="EDIT",
        help=f"edit kinds ({', '.join(EDITS)})",
    )
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    return run_in_work(args.work, lambda work: _run(args, work))


def _cached(path: Path, make: Callable[[], Path]) -> Path:
    return path if path.exists() else make()


@dataclasses.dataclass(frozen=True)
class Setup:
    """The bench's Cornell box, its two caches and its edits.

    Attributes:
        shot: the written stage; camera_path: its camera prim.
        shot_layer, shot_label, sizes: the shot cache, its row label and its baked sizes.
        direct_layer: the direct cache.
        rigs: edit kind -> k -> (rig before, rig after) (`edit_rigs`).
    """

    shot: Path
    camera_path: str
    shot_layer: Path
    shot_label: str
    sizes: object
    direct_layer: Path
    rigs: dict[str, Callable[[int], tuple[Rig, Rig]]]


def prepare(args: argparse.Namespace, work: Path) -> Setup:
    """Write the Cornell box into `work`, take or bake its shot and direct caches at --width x
    --height (args.shot_cache, args.direct_cache, args.shot_size, args.quality) and make the edits."""
    work.mkdir(parents=True, exist_ok=True)
    shot = SCENES[SCENE].write(work / "scene")
    camera_path = SCENES[SCENE].camera

    def full():  # the scene at --width x --height and its camera, for a bake only
        scene = load_scene(shot, width=args.width, height=args.height)
        return scene, find_camera(scene, camera_path)

    if args.shot_cache is not None:
        shot_layer = args.shot_cache
        description = read_cache_layer(shot_layer)
        kept = ("supersampling", "gathers", "coefficients", "bounceCoefficients", "bounces", "indirectScale")
        sizes: object = {name: description.parameters[name] for name in kept if name in description.parameters}
        label = f"shot sizes ({description.method})"
    else:
        small = load_scene(shot, width=args.shot_size[0], height=args.shot_size[1])
        choice, result = bake_shot(small, find_camera(small, camera_path), work / "shot-choice", SCENE, args.quality)
        method = "direct" if choice.components == "direct" else "transfer"
        shot_layer = _cached(
            work / "shot" / f"{SCENE}.relight.usda",
            lambda: bake_method(method).adapter.bake(*full(), work / "shot", SCENE, result.point, 1, 2),
        )
        sizes, label = result.point, f"shot ({choice.components})"
    direct_layer = args.direct_cache or _cached(
        work / "direct" / f"{SCENE}.relight.usda",
        lambda: bake_direct(*full(), work / "direct", SCENE, supersampling=2),
    )
    description = read_cache_layer(direct_layer)
    lights = shot_lights(description)
    layer = new_sphere_layer(shot, camera_path, work / "new_light.usda")
    new_light = next(light for light in shot_lights(description, layer) if light.path == NEW_LIGHT_PATH)
    return Setup(shot, camera_path, shot_layer, label, sizes, direct_layer, edit_rigs(lights, new_light))


def references_of(setup: Setup, edits, size: tuple[int, int], spp: int, work: Path) -> dict[str, np.ndarray]:
    """Edit kind -> the path tracer's full frame (H', W', 3) at `size` = (W', H') of the rig after
    its edit k = 0, rendered once and kept in `work`."""
    reference_scene = load_scene(setup.shot, width=size[0], height=size[1])
    reference_camera = find_camera(reference_scene, setup.camera_path)
    references = {}
    for edit, rig in setup.rigs.items():
        if edit not in edits:
            continue
        path = work / f"reference-{edit.replace(' ', '_')}-{size[0]}-{spp}.npy"
        if not path.exists():
            np.save(path, reference_image(reference_scene, reference_camera, rig(0)[1], spp))
        references[edit] = np.load(path)
    return references


def _run(args: argparse.Namespace, work: Path) -> int:
    load = os.getloadavg()
    setup = prepare(args, work)
    references = references_of(setup, args.edits, tuple(args.reference_size), args.spp, work)
    rows = measure(setup.shot_layer, setup.shot_label, setup.rigs, args, references)
    rows += measure(setup.direct_layer, "direct", setup.rigs, args, references)
    _write(args, rows, setup.sizes, load + os.getloadavg())
    return 0


def _write(args: argparse.Namespace, rows: list[dict[str, object]], point, load: tuple[float, ...]) -> None:
    """progressive.csv and summary.md in args.out."""
    lines = [",".join(FIELDS)]
    for row in rows:
        lines.append(",".join(csv_cell(row.get(name, "")) for name in FIELDS))
    write_text_atomic(args.out / "progressive.csv", "\n".join(lines) + "\n")
    command = (
        f"python -m pipeline.benchmarks.progressive --width {args.width} --height {args.height} --shot-size "
        f"{args.shot_size[0]} {args.shot_size[1]} --quality {args.quality:g} --repeats {args.repeats} --budget-ms "
        f"{args.budget_ms:g} --reference-size {args.reference_size[0]} {args.reference_size[1]} --spp {args.spp} "
        f"--out {args.out}"
        + ("" if list(args.edits) == list(EDITS) else " --edits " + " ".join(f"'{edit}'" for edit in args.edits))
        + (f" --shot-cache {args.shot_cache} --direct-cache {args.direct_cache}" if args.shot_cache else "")
    )
    text = [
        "# Progressive relighting: the first frame after each edit, and the converged one",
        "",
        f"Generated by `{command}`.",
        "",
        f"Cornell box at {args.width}x{args.height}, budget {args.budget_ms:g} ms. The shot cache: {point}. "
        "Each figure is the median of "
        f"{args.repeats} edits after a warm-up one; levels are 1/p (one shaded point per p x p pixels, "
        "upsampled edge-aware) or exact. PSNR against the reference: the path tracer's full frame at "
        f"{args.reference_size[0]}x{args.reference_size[1]}, {args.spp} spp, the relit frames box-filtered "
        "to it. First frame: wall ms, and in brackets the process's CPU ms (all threads), the work itself "
        "on a shared machine. 'max diff' is the converged frame against a fresh relighter's render(). "
        "Per level: the median "
        "ms of its frame and the median PSNR of its frame against the converged one.",
        "",
        "| cache | edit | first frame ms (CPU ms) | level | first vs converged dB | converged ms | max diff | "
        "first vs reference dB | converged vs reference dB | median ms per level | median dB per level |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        if row.get("note"):
            text.append(f"| {row['cache']} | {row['edit']} | {row['note']} |  |  |  |  |  |  |  |  |")
            continue
        text.append(
            f"| {row['cache']} | {row['edit']} | {row['first_ms']:.1f} ({row['first_cpu_ms']:.0f}) | "
            f"{row['first_level']} | "
            f"{row['first_psnr_vs_converged_db']:.1f} | {row['converged_ms']:.0f} | {row['converged_max_diff']:.1e} | "
            f"{row['first_psnr_vs_reference_db']:.1f} | {row['converged_psnr_vs_reference_db']:.1f} | "
            f"{row['level_ms']} | {row['level_psnr_db']} |"
        )
    text += [
        "",
        f"Machine: {machine_description()}; load average {load[0]:.1f} / {load[3]:.1f} (1 min, start / end): "
        "the machine was shared with other work, so the times are medians under load; re-run the command "
        "on a quiet machine for clean figures.",
        "",
    ]
    write_text_atomic(args.out / "summary.md", "\n".join(text))


def csv_cell(value: object) -> str:
    """One CSV cell: floats to 6 significant digits, None empty, text with a comma quoted."""
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    text = str(value)
    return f'"{text}"' if "," in text else text


if __name__ == "__main__":
    raise SystemExit(main())
