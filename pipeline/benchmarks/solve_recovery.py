"""Recovery of known rig changes by `relight solve`, on the bundled scenes (docs/SOLVE.md).

Per scene: a direct cache is baked (default texture samples, what users get); the rig is changed
by known amounts (every light's intensity scaled by a factor from 0.5 to 2, its colour's green and
blue changed, the first movable light moved by 10 % of the scene's diagonal along the first
direction that keeps it in the room, `clear_move`); `relight reference` renders the target (direct
light: the cache's method models direct light only); the solve starts from the unchanged rig.
Reported: the largest intensity error (relative), colour error (largest component, colours
normalised to their largest component), position error over the diagonal, PSNR of the solved rig
rendered by `relight reference` against the target, gradient steps, seconds, and what the solve
says the target leaves open. More experiments: the same changes with the move along
MOVE_DIRECTIONS[0] where that takes the light out of the room (`run_scene(out_of_room=True)`: the
solve cannot follow it and must say so), a cone 20 % wider (`run_cone`) and a painted target
(`run_painted`). Writes docs/bench/solve/summary.md.

    python -m pipeline.benchmarks.solve_recovery --width 96 --height 72 --out docs/bench/solve
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from pipeline.bake.direct.bake import bake_direct
from pipeline.cli import main as relight
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES
from pipeline.tracing import Tracer
from relight_torch.cache.layer import read_cache_layer
from relight_torch.direct import gradients
from relight_torch.direct.loading import shot_lights
from relight_torch.direct.relighter import open_relighter
from relight_torch.io.exr import read_rgb_exr
from relight_torch.lights.light import Light
from relight_torch.lights.overrides import write_light_overrides
from relight_torch.metrics import psnr
from relight_torch.solve import DescentSettings, solve_lights

FACTORS = (0.5, 2.0, 0.7, 1.5, 1.2)
MOVE = 0.1
"""The move, in units of the scene's diagonal."""
MOVE_MARGIN = 0.02
"""Clearance the moved light keeps beyond and beside its new position, in units of the diagonal
(the position goal: a light solved within it stays on the same side of every surface)."""
MOVE_DIRECTIONS = tuple(
    (0.6 * np.cos(angle) + 0.8 * np.sin(angle), 0.0, 0.6 * np.sin(angle) - 0.8 * np.cos(angle))
    for angle in np.radians(np.arange(0.0, 360.0, 45.0))
) + ((0.0, 1.0, 0.0), (0.0, -1.0, 0.0))
"""Candidate move directions (world, +Y up), tried in this order: (0.6, 0, -0.8), the bench's
first, turned about the vertical in 45 degree steps, then up and down."""


def stays_in_room(tracer: Tracer, start: np.ndarray, end: np.ndarray, bounds: np.ndarray, margin: float) -> bool:
    """Whether a light moved from `start` to `end` (3,) stays in the room: `end` no further outside
    `bounds` (2, 3), the box of what the camera sees, than `start` along any axis (a key light above
    an open scene may move across it), and nothing of the scene on the segment from `start` to
    `margin` past `end`, nor within `margin` of `end` across the move (horizontally). An unoccluded
    segment alone is not enough: the set's window light, moved along MOVE_DIRECTIONS[0], leaves the
    hall through its window opening."""

    def outside(point: np.ndarray) -> np.ndarray:
        return np.maximum(np.maximum(bounds[0] - point, point - bounds[1]), 0.0)

    if np.any(outside(end) > outside(start)):
        return False
    length = float(np.linalg.norm(end - start))
    direction = (end - start) / length
    across = np.cross(direction, (0.0, 1.0, 0.0))
    if not across.any():  # a vertical move: across it along x
        across = np.array([1.0, 0.0, 0.0])
    across = across / np.linalg.norm(across)
    origins = np.array([start, end, end], np.float32)
    directions = np.array([direction, across, -across], np.float32)
    t_far = np.array([length + margin, margin, margin], np.float32)
    return not bool(tracer.occluded(origins, directions, t_far).any())


def clear_move(tracer: Tracer, start: np.ndarray, bounds: np.ndarray, diagonal: float) -> np.ndarray:
    """(3,) the move by MOVE x `diagonal` along the first of MOVE_DIRECTIONS that keeps a light at
    `start` in the room (`stays_in_room`, MOVE_MARGIN x `diagonal` of clearance).

    Raises:
        RuntimeError: no direction is clear (one line).
    """
    for direction in np.asarray(MOVE_DIRECTIONS):
        offset = MOVE * diagonal * direction
        if stays_in_room(tracer, start, start + offset, bounds, MOVE_MARGIN * diagonal):
            return offset
    raise RuntimeError(
        f"no move of {MOVE:.0%} of the diagonal from {start.tolist()} stays in the room along any of "
        f"{len(MOVE_DIRECTIONS)} directions"
    )


def movable_light(lights: list[Light]) -> Light | None:
    """The light the experiments move: the first whose position is free to solve."""
    return next((light for light in lights if gradients.applies("position", light)), None)


def changed_rig(lights: list[Light], offset: np.ndarray) -> tuple[list[Light], str | None]:
    """The rig with known changes (module doc), the `movable_light` translated by `offset` (3,)
    world units, and that light's path (None if none moves)."""
    movable = movable_light(lights)
    moved_path = None if movable is None else movable.path
    changed = []
    for index, light in enumerate(lights):
        colour = (light.color[0], light.color[1] * 0.8, light.color[2] * 1.2)
        light = dataclasses.replace(light, intensity=light.intensity * FACTORS[index % len(FACTORS)], color=colour)
        if light.path == moved_path:
            matrix = light.world_from_light.copy()
            matrix[:3, 3] += offset
            light = dataclasses.replace(light, world_from_light=matrix)
        changed.append(light)
    return changed, moved_path


def reference(shot: Path, camera: str, size: tuple[int, int], before, after, out: Path, spp: int) -> np.ndarray:
    lights = out.with_suffix(".lights.usda")
    write_light_overrides(lights, before, after)
    argv = ["reference", str(shot), "--camera", camera, "--width", str(size[0]), "--height", str(size[1])]
    argv += ["--spp", str(spp), "--max-bounces", "0", "--lights", str(lights), "-o", str(out)]
    if relight(argv) != 0:
        raise RuntimeError(f"reference failed for {shot}")
    return read_rgb_exr(out)


def bake(name: str, size: tuple[int, int], directory: Path) -> tuple[Path, Path]:
    """(shot, direct cache layer) of bundled scene `name` at `size`, under directory/name (made
    once), at the default texture samples (what `relight bake` gives users)."""
    spec = SCENES[name]
    layer = directory / name / "cache" / f"{name}.relight.usda"
    shot = directory / name / "scene" / f"{name}.usda"
    if not layer.is_file():
        shot = spec.write(directory / name / "scene")
        scene = load_scene(shot, width=size[0], height=size[1])
        layer = bake_direct(scene, find_camera(scene, spec.camera), directory / name / "cache", name)
    return shot, layer


def run_scene(
    name: str,
    size: tuple[int, int],
    spp: int,
    iterations: int,
    directory: Path,
    robust: bool = False,
    out_of_room: bool = False,
) -> dict[str, object] | None:
    """The recovery experiment (module doc) on one scene; with `out_of_room`, the first movable
    light moved along MOVE_DIRECTIONS[0] whatever is in the way, and None unless that takes it out
    of the room (`stays_in_room`): a move no local step can follow, which the solve must flag."""
    spec = SCENES[name]
    shot, layer = bake(name, size, directory)
    before = shot_lights(read_cache_layer(layer))
    relighter = open_relighter(layer)
    diagonal = relighter.scene_diagonal()
    position = relighter.gbuffer.position.to(torch.float64)
    bounds = torch.stack((position.amin(0), position.amax(0))).numpy()
    tracer = Tracer.for_scene(load_scene(shot, width=size[0], height=size[1]))
    movable = movable_light(before)
    offset = np.zeros(3)
    if movable is not None:
        origin = movable.world_from_light[:3, 3]
        if not out_of_room:
            offset = clear_move(tracer, origin, bounds, diagonal)
        else:
            offset = MOVE * diagonal * np.asarray(MOVE_DIRECTIONS[0])
            if stays_in_room(tracer, origin, origin + offset, bounds, MOVE_MARGIN * diagonal):
                return None
    elif out_of_room:
        return None
    truth, moved = changed_rig(before, offset)
    stem = "out_of_room_" if out_of_room else ""
    target = reference(shot, spec.camera, size, before, truth, directory / name / f"{stem}target.exr", spp)
    free = "intensity,color" + (",position" if moved else "")
    start = time.perf_counter()
    result = solve_lights(
        relighter, torch.from_numpy(target), free=free, settings=DescentSettings(iterations=iterations), robust=robust
    )
    seconds = time.perf_counter() - start
    solved = {light.path: light for light in result.after}
    intensity, colour, position_error = 0.0, 0.0, 0.0
    for light in truth:
        got = solved[light.path]
        want_emission = light.intensity * max(light.color)
        if want_emission > 0:
            intensity = max(intensity, abs(got.intensity * max(got.color) / want_emission - 1.0))
            normalised = np.asarray(got.color) / max(max(got.color), 1e-30) - np.asarray(light.color) / max(light.color)
            colour = max(colour, float(np.abs(normalised).max()))
        if light.path == moved:
            position_error = (
                float(np.linalg.norm(got.world_from_light[:3, 3] - light.world_from_light[:3, 3])) / diagonal
            )
    solved_image = reference(shot, spec.camera, size, before, result.after, directory / name / f"{stem}solved.exr", spp)
    return {
        "scene": name,
        "out_of_room": out_of_room,
        "moved": moved,
        "direction": tuple(round(float(v), 2) for v in offset / max(float(np.linalg.norm(offset)), 1e-30)),
        "lights": len(before),
        "free": free,
        "intensity_error": intensity,
        "colour_error": colour,
        "position_error": position_error,
        "psnr_db": float(psnr(torch.from_numpy(solved_image), torch.from_numpy(target))),
        "iterations": result.iterations,
        "seconds": seconds,
        "unresolved": "; ".join(result.unresolved) or "none",
    }


def run_cone(
    name: str, size: tuple[int, int], spp: int, iterations: int, directory: Path, robust: bool = False
) -> dict[str, object] | None:
    """The first light with ShapingAPI gets a cone 20 % wider; the solve frees its intensity and
    shaping alone. None when the scene has no shaped light."""
    spec = SCENES[name]
    shot, layer = bake(name, size, directory)
    before = shot_lights(read_cache_layer(layer))
    shaped = next((light for light in before if gradients.applies("shaping", light)), None)
    if shaped is None or shaped.shaping is None:
        return None
    wider = dataclasses.replace(shaped.shaping, cone_angle=shaped.shaping.cone_angle * 1.2)
    truth = [dataclasses.replace(light, shaping=wider) if light.path == shaped.path else light for light in before]
    target = reference(shot, spec.camera, size, before, truth, directory / name / "cone_target.exr", spp)
    relighter = open_relighter(layer)
    start = time.perf_counter()
    result = solve_lights(
        relighter, torch.from_numpy(target), solve=[shaped.path], free="intensity,shaping",
        settings=DescentSettings(iterations=iterations), robust=robust,
    )  # fmt: skip
    seconds = time.perf_counter() - start
    got = next(light for light in result.after if light.path == shaped.path)
    assert got.shaping is not None
    solved_image = reference(shot, spec.camera, size, before, result.after, directory / name / "cone_solved.exr", spp)
    return {
        "scene": name,
        "light": shaped.path,
        "cone": (shaped.shaping.cone_angle, wider.cone_angle, got.shaping.cone_angle),
        "softness": (wider.cone_softness, got.shaping.cone_softness),
        "focus": (wider.focus, got.shaping.focus),
        "intensity_error": abs(got.intensity / shaped.intensity - 1.0),
        "psnr_db": float(psnr(torch.from_numpy(solved_image), torch.from_numpy(target))),
        "iterations": result.iterations,
        "seconds": seconds,
    }


def run_painted(name: str, size: tuple[int, int], directory: Path) -> dict[str, object]:
    """A relit frame brightened twice inside a rectangle (the middle ninth) and left elsewhere; the
    closed form over every light's intensity and colour, all pixels weighted alike. Reported: the
    relative error of the solved frame against the painted target inside and outside the rectangle,
    and the painted change itself inside (1.0: the frame before the solve)."""
    _, layer = bake(name, size, directory)
    relighter = open_relighter(layer)
    frame = relighter.render().to(torch.float64)
    height, width = frame.shape[:2]
    inside = torch.zeros(height, width, dtype=torch.bool)
    inside[height // 3 : 2 * height // 3, width // 3 : 2 * width // 3] = True
    target = torch.where(inside.unsqueeze(-1), 2.0 * frame, frame)
    result = solve_lights(relighter, target, free="intensity,color")
    solved = relighter.render().to(torch.float64)

    def relative(region: torch.Tensor, image: torch.Tensor) -> float:
        mask = region.unsqueeze(-1).expand_as(image)
        return float(((image - target)[mask].square().mean() / target[mask].square().mean()).sqrt())

    return {
        "scene": name,
        "before_inside": relative(inside, frame),
        "inside": relative(inside, solved),
        "outside": relative(~inside, solved),
        "mean_ratio_inside": float(solved[inside].mean() / frame[inside].mean()),
        "seconds": result.seconds,
    }


def table(header: list[str], rows: list[list[object]]) -> list[str]:
    """Markdown lines of a table (a blank line first)."""
    lines = ["", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return lines + ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]


def write_summary(
    rows: list[dict[str, object]],
    extra: list[dict[str, object]],
    out: Path,
    size: tuple[int, int],
    spp: int,
    command: str,
) -> None:
    lines = [
        "# relight solve: recovery of known rig changes",
        "",
        f"Direct caches at {size[0]}x{size[1]}, targets by `relight reference --max-bounces 0 --spp {spp}`; "
        "every light's intensity scaled (x0.5 to x2) and colour changed, the first movable light moved by 10 % "
        "of the scene's diagonal along the first of eight horizontal directions (then up, down) that keeps it in "
        "the room (inside the box of what the camera sees, nothing in its way or within 2 % of the diagonal of "
        "where it lands); caches baked at the default texture samples; the solve starts from the unchanged rig. "
        "Errors: intensity relative (largest over lights), colour absolute on colours normalised to their "
        "largest component, position over the diagonal; PSNR of the solved rig rendered by `relight reference` "
        "against the target (both noisy at this spp). Seconds on the shared 2-core machine (disturbed by other "
        "work: re-measure on a quiet one).",
        "",
        f"Command: `{command}`",
    ]
    header = ["scene", "lights", "free", "moved light, direction", "intensity err", "colour err", "position err / diag",
              "PSNR dB", "steps", "s", "what the target leaves open (`relight solve` warns)"]  # fmt: skip

    def cells(row: dict[str, object]) -> list[object]:
        moved = f"{row['moved']} {row['direction']}" if row["moved"] else "none"
        return [row["scene"], row["lights"], row["free"], moved, f"{row['intensity_error']:.2%}",
                f"{row['colour_error']:.4f}", f"{row['position_error']:.2%}", f"{row['psnr_db']:.1f}",
                row["iterations"], f"{row['seconds']:.1f}", row["unresolved"]]  # fmt: skip

    recovered = [row for row in rows if not row["out_of_room"]]
    if recovered:
        lines += table(header, [cells(row) for row in recovered])
    outside = [row for row in rows if row["out_of_room"]]
    if outside:
        lines += [
            "",
            "## A light moved out of the room (the same changes, the move along "
            f"{tuple(round(float(v), 2) for v in MOVE_DIRECTIONS[0])} whatever is in the way)",
            "",
            "No local step follows a light through an occluder (visibility has no gradient): the solve cannot "
            "recover it, and must say so in its last column.",
        ]
        lines += table(header, [cells(row) for row in outside])
    cones = [row for row in extra if "cone" in row]
    if cones:
        lines += ["", "## A cone 20 % wider (intensity and shaping free, that light alone)"]
        lines += table(
            ["scene", "light", "cone start / truth / solved (deg)", "softness truth / solved", "focus truth / solved",
             "intensity err", "PSNR dB", "steps", "s"],
            [
                [row["scene"], row["light"], " / ".join(f"{v:.1f}" for v in row["cone"]),
                 " / ".join(f"{v:.2f}" for v in row["softness"]), " / ".join(f"{v:.2f}" for v in row["focus"]),
                 f"{row['intensity_error']:.2%}", f"{row['psnr_db']:.1f}", row["iterations"], f"{row['seconds']:.1f}"]
                for row in cones
            ],
        )  # fmt: skip
    painted = [row for row in extra if "inside" in row]
    if painted:
        lines += [
            "",
            "## Painted targets: the relit frame brightened x2 in the middle ninth",
            "",
            "Closed form over every light's intensity and colour, all pixels weighted alike. Relative RMS error "
            "against the painted target inside and outside the painted rectangle (before the solve: the "
            "inside error of the unpainted frame, 0 outside); mean brightness gain inside (2 is the paint's).",
        ]
        lines += table(
            ["scene", "inside before", "inside after", "outside after", "gain inside", "s"],
            [
                [row["scene"], f"{row['before_inside']:.3f}", f"{row['inside']:.3f}", f"{row['outside']:.3f}",
                 f"{row['mean_ratio_inside']:.2f}", f"{row['seconds']:.1f}"]
                for row in painted
            ],
        )  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.md").write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["cornell_box", "glossy", "set"])
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--spp", type=int, default=256)
    parser.add_argument("--iterations", type=int, default=200)
    parser.add_argument("--out", type=Path, default=Path("docs/bench/solve"))
    parser.add_argument("--robust", action="store_true", help="solve under Huber's loss (`relight solve --robust`)")
    parser.add_argument(
        "--experiments",
        nargs="+",
        default=["recovery", "out_of_room", "cone", "painted"],
        choices=("recovery", "out_of_room", "cone", "painted"),
    )
    args = parser.parse_args(argv)
    size = (args.width, args.height)
    rows: list[dict[str, object]] = []
    extra: list[dict[str, object]] = []
    command = (
        f"python -m pipeline.benchmarks.solve_recovery --scenes {' '.join(args.scenes)} --width {args.width} "
        f"--height {args.height} --spp {args.spp} --iterations {args.iterations} "
        f"--experiments {' '.join(args.experiments)}" + (" --robust" if args.robust else "")
    )
    with tempfile.TemporaryDirectory() as directory:
        for name in args.scenes:
            for out_of_room in [experiment == "out_of_room" for experiment in args.experiments
                                if experiment in ("recovery", "out_of_room")]:  # fmt: skip
                row = run_scene(name, size, args.spp, args.iterations, Path(directory), args.robust, out_of_room)
                if row is not None:
                    rows.append(row)
                    print(row, flush=True)
            if "cone" in args.experiments:
                cone = run_cone(name, size, args.spp, args.iterations, Path(directory), args.robust)
                if cone is not None:
                    extra.append(cone)
                    print(cone, flush=True)
            if "painted" in args.experiments:
                extra.append(run_painted(name, size, Path(directory)))
                print(extra[-1], flush=True)
            write_summary(rows, extra, args.out, size, args.spp, command)  # after each scene: slow runs keep theirs
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
