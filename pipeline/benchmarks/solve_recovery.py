"""Recovery of known rig changes by `relight solve`, on the bundled scenes (docs/SOLVE.md).

Per scene: a direct cache is baked; the rig is changed by known amounts (every light's intensity
scaled by a factor from 0.5 to 2, its colour's green and blue changed, the first movable light
moved by 10 % of the scene's diagonal); `relight reference` renders the target (direct light: the
cache's method models direct light only); the solve starts from the unchanged rig. Reported:
the largest intensity error (relative), colour error (largest component, colours normalised to
their largest component), position error over the diagonal, PSNR of the solved rig rendered by
`relight reference` against the target, gradient steps and seconds. Two more experiments: a cone
20 % wider (`run_cone`) and a painted target (`run_painted`). Writes docs/bench/solve/summary.md.

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


def changed_rig(lights: list[Light], diagonal: float) -> tuple[list[Light], str | None]:
    """The rig with known changes (module doc) and the path of the moved light (None if none moves)."""
    moved_path = next((light.path for light in lights if gradients.applies("position", light)), None)
    changed = []
    for index, light in enumerate(lights):
        colour = (light.color[0], light.color[1] * 0.8, light.color[2] * 1.2)
        light = dataclasses.replace(light, intensity=light.intensity * FACTORS[index % len(FACTORS)], color=colour)
        if light.path == moved_path:
            matrix = light.world_from_light.copy()
            matrix[:3, 3] += 0.1 * diagonal * np.array([0.6, 0.0, -0.8])
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
    """(shot, direct cache layer) of bundled scene `name` at `size`, under directory/name (made once)."""
    spec = SCENES[name]
    layer = directory / name / "cache" / f"{name}.relight.usda"
    shot = directory / name / "scene" / f"{name}.usda"
    if not layer.is_file():
        shot = spec.write(directory / name / "scene")
        scene = load_scene(shot, width=size[0], height=size[1])
        layer = bake_direct(scene, find_camera(scene, spec.camera), directory / name / "cache", name, texture_samples=1)
    return shot, layer


def scene_diagonal(relighter) -> float:
    position = relighter.gbuffer.position
    return float((position.amax(0) - position.amin(0)).norm())


def run_scene(
    name: str, size: tuple[int, int], spp: int, iterations: int, directory: Path, robust: bool = False
) -> dict[str, object]:
    """The recovery experiment (module doc) on one scene."""
    spec = SCENES[name]
    shot, layer = bake(name, size, directory)
    before = shot_lights(read_cache_layer(layer))
    relighter = open_relighter(layer)
    diagonal = scene_diagonal(relighter)
    truth, moved = changed_rig(before, diagonal)
    target = reference(shot, spec.camera, size, before, truth, directory / name / "target.exr", spp)
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
    solved_image = reference(shot, spec.camera, size, before, result.after, directory / name / "solved.exr", spp)
    return {
        "scene": name,
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
        "of the scene's diagonal; the solve starts from the unchanged rig. Errors: intensity relative (largest "
        "over lights), colour absolute on colours normalised to their largest component, position over the "
        "diagonal; PSNR of the solved rig rendered by `relight reference` against the target (both noisy at "
        "this spp). Seconds on the shared 2-core machine (disturbed by other work: re-measure on a quiet one).",
        "",
        f"Command: `{command}`",
    ]
    if rows:
        lines += table(
            ["scene", "lights", "free", "intensity err", "colour err", "position err / diag", "PSNR dB", "steps", "s",
             "what the target leaves open (`relight solve` warns)"],
            [
                [row["scene"], row["lights"], row["free"], f"{row['intensity_error']:.2%}",
                 f"{row['colour_error']:.4f}", f"{row['position_error']:.2%}", f"{row['psnr_db']:.1f}",
                 row["iterations"], f"{row['seconds']:.1f}", row["unresolved"]]
                for row in rows
            ],
        )  # fmt: skip
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
        "--experiments", nargs="+", default=["recovery", "cone", "painted"], choices=("recovery", "cone", "painted")
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
            if "recovery" in args.experiments:
                rows.append(run_scene(name, size, args.spp, args.iterations, Path(directory), args.robust))
                print(rows[-1], flush=True)
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
