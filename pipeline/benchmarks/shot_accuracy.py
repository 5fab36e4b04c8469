"""The shot cache against the full frame: accuracy per light edit, and edit timings.

    python -m pipeline.benchmarks.shot_accuracy SCENE [SCENE ...] --width 320 --height 240 --spp 1024 \
        [--quality 35] [--timing-size 640 480] [--repeats 7] --out docs/bench/shot [--work DIR]

Per bundled scene: the default bake (`pipeline.bake.shot.bake_shot`) at the given size, then per light
edit (the shot, the scene's example edits and a new sphere light) the relit frame against
`relight reference --max-bounces 8` at `--spp`: PSNR, relMSE, the energy ratio mean(x) / mean(y), and
the indirect part alone (relit minus its direct component, against the full reference minus the
direct-only one) as relMSE and energy ratio. With `--timing-size W H` the chosen sizes are baked again
at that size (no reference) and each edit kind is timed: median ms of the edit and the re-render, warm.
Writes shot.csv and summary.md (the tables and this command) into --out.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import datetime
import time
from pathlib import Path

import numpy as np

from pipeline.bake.adapter import cache_bytes
from pipeline.bake.methods import bake_method
from pipeline.bake.shot import DEFAULT_TARGET_DB, bake_shot
from pipeline.benchmarks import run_in_work
from pipeline.benchmarks.bench.measure import machine_description, moved
from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES, light_edit_layers
from pipeline.scenes.lights import NEW_LIGHT_PATH, new_sphere_layer
from pipeline.tracing_bench import median_seconds
from relight_torch import open_cache
from relight_torch.cache.layer import read_cache_layer
from relight_torch.direct.relighter import shot_lights
from relight_torch.indirect import IndirectRelighter
from relight_torch.io.atomic import write_text_atomic
from relight_torch.lights.light import Shaping
from relight_torch.metrics import psnr, rel_mse
from relight_torch.protocol import CacheRelighter

REFERENCE_BOUNCES = 8


@dataclasses.dataclass(frozen=True)
class EditRow:
    """One edit's figures against the full frame."""

    scene: str
    edit: str
    psnr_db: float
    rel_mse: float
    energy_ratio: float
    indirect_rel_mse: float
    indirect_energy_ratio: float


def _reference(
    scene_path: Path, camera: str, width: int, height: int, layer: Path | None, bounces: int, spp: int, directory: Path
) -> np.ndarray:
    """The path tracer's (H, W, 3) image, kept as .npy in `directory` between runs."""
    path = directory / f"reference-{'shot' if layer is None else layer.stem}-{bounces}-{spp}.npy"
    if not path.exists():
        scene = load_scene(scene_path, lights_layer=layer, width=width, height=height)
        image = PathTracer(scene, ReferenceSettings(spp=spp, max_bounces=bounces)).render(find_camera(scene, camera))
        np.save(path, image.mean)
    return np.load(path)


def _indirect_image(relighter: CacheRelighter, components: str, layer: Path, image: np.ndarray) -> np.ndarray:
    """(H, W, 3) the indirect part of a shot cache's render: none for a 'direct' shot, the indirect
    relighter's own for 'direct+transfer' (`shotComponents`, `pipeline.bake.shot`)."""
    if components == "direct":
        return np.zeros_like(image)
    if not isinstance(relighter, IndirectRelighter):
        raise TypeError(f"{layer}: shotComponents {components!r}, but its relighter is a {type(relighter).__name__}")
    return relighter.indirect_image().numpy()


def accuracy_rows(
    name: str,
    layer: Path,
    scene_path: Path,
    edits: dict[str, Path | None],
    width: int,
    height: int,
    spp: int,
    directory: Path,
) -> list[EditRow]:
    """One EditRow per edit of the shot cache `layer` (see the module doc)."""
    camera = SCENES[name].camera
    description = read_cache_layer(layer)
    relighter = open_cache(layer)
    components = str(description.parameters["shotComponents"])
    rows = []
    for edit, lights_layer in edits.items():
        relighter.set_lights(shot_lights(description, lights_layer))
        image = relighter.render().numpy()
        indirect = _indirect_image(relighter, components, layer, image)
        full = _reference(scene_path, camera, width, height, lights_layer, REFERENCE_BOUNCES, spp, directory)
        zero = _reference(scene_path, camera, width, height, lights_layer, 0, spp, directory)
        reference_indirect = full - zero
        rows.append(
            EditRow(
                name,
                edit,
                psnr(image, full),
                rel_mse(image, full),
                float(image.mean() / full.mean()),
                rel_mse(indirect, reference_indirect),
                float(indirect.mean() / max(float(reference_indirect.mean()), 1e-12)),
            )
        )
    return rows


def edit_timings(layer: Path, edits: dict[str, Path | None], repeats: int) -> dict[str, float]:
    """Median ms of each edit kind and the re-render on a warm relighter of `layer`."""
    description = read_cache_layer(layer)
    relighter = open_cache(layer)
    lights = shot_lights(description, None)
    relighter.set_lights(lights)
    relighter.render()
    first = lights[0]
    added = next(light for light in shot_lights(description, edits["new_light"]) if light.path == NEW_LIGHT_PATH)
    toggles = iter(range(1 << 30))

    def timed(edit) -> float:
        def run() -> None:
            edit(next(toggles) % 2)
            relighter.render()

        return 1e3 * median_seconds(run, repeats)

    colours = (first, dataclasses.replace(first, color=(first.color[0], 0.8 * first.color[1], 0.6 * first.color[2])))
    shaping = first.shaping or Shaping()
    shaped = (first, dataclasses.replace(first, shaping=dataclasses.replace(shaping, focus=shaping.focus + 2.0)))
    timings = {
        "colour": timed(lambda k: relighter.set_light(colours[k])),
        "shaping": timed(lambda k: relighter.set_light(shaped[k])),
        "move": timed(lambda k: relighter.set_light(moved(first, 0.01 * (1 + k)))),
        "new light": timed(lambda k: relighter.set_light(added) if k == 0 else relighter.remove_light(added.path)),
    }
    relighter.set_lights(lights)
    return timings


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", nargs="+", choices=sorted(SCENES))
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--spp", type=int, default=1024)
    parser.add_argument("--quality", type=float, default=DEFAULT_TARGET_DB)
    parser.add_argument("--timing-size", type=int, nargs=2, metavar=("W", "H"))
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument(
        "--work",
        type=Path,
        help="where bakes and references go, kept between runs (default: a temporary directory, removed)",
    )
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    return run_in_work(args.work, lambda work: _run(args, work))


def _run(args: argparse.Namespace, work: Path) -> int:
    """Measure every scene of `args` with its bakes and references in `work`; write the tables."""
    work.mkdir(parents=True, exist_ok=True)
    rows, choices = [], []
    for name in args.scenes:
        scene_path = SCENES[name].write(work)
        edits = light_edit_layers(name, work) | {
            "new_light": new_sphere_layer(scene_path, SCENES[name].camera, work / f"{name}.lights.new_light.usda")
        }
        scene = load_scene(scene_path, width=args.width, height=args.height)
        camera = find_camera(scene, SCENES[name].camera)
        start = time.perf_counter()
        choice, result = bake_shot(scene, camera, work / f"{name}-cache", name, args.quality)
        bake_s = time.perf_counter() - start
        rows += accuracy_rows(name, result.layer, scene_path, edits, args.width, args.height, args.spp, work)
        timings = {}
        if args.timing_size:
            big = load_scene(scene_path, width=args.timing_size[0], height=args.timing_size[1])
            big_camera = find_camera(big, SCENES[name].camera)
            method = "direct" if choice.components == "direct" else "transfer"
            big_layer = bake_method(method).adapter.bake(
                big, big_camera, work / f"{name}-timing", name, result.point, 1, 2
            )
            timings = edit_timings(big_layer, edits, args.repeats)
        choices.append((name, choice, result, bake_s, cache_bytes(result.layer), timings))
    _write(args, rows, choices)
    return 0


def _write(args: argparse.Namespace, rows: list[EditRow], choices: list) -> None:
    """shot.csv and summary.md in args.out."""
    fields = [field.name for field in dataclasses.fields(EditRow)]
    with open(args.out / "shot.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(fields)
        writer.writerows([[getattr(row, f) for f in fields] for row in rows])
    command = (
        f"python -m pipeline.benchmarks.shot_accuracy {' '.join(args.scenes)} --width {args.width} "
        f"--height {args.height} --spp {args.spp} --quality {args.quality:g}"
        + (f" --timing-size {args.timing_size[0]} {args.timing_size[1]}" if args.timing_size else "")
        + f" --repeats {args.repeats} --out {args.out}"
    )
    lines = [
        "# The shot cache against the full frame",
        "",
        f"Generated by `{command}`.",
        "",
        f"Accuracy at {args.width}x{args.height} against the path tracer ({REFERENCE_BOUNCES} bounces, "
        f"{args.spp} spp); the indirect part is the relit frame less its direct component against the "
        "full reference less the direct-only one.",
        "",
        "| scene | edit | PSNR dB | relMSE | energy ratio | indirect relMSE | indirect energy ratio |",
        "|---|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {r.scene} | {r.edit} | {r.psnr_db:.2f} | {r.rel_mse:.4f} | {r.energy_ratio:.3f} | "
        f"{r.indirect_rel_mse:.4f} | {r.indirect_energy_ratio:.3f} |"
        for r in rows
    ]
    lines += [
        "",
        "| scene | components | bounces | sizes | pilot dB | measured dB | energy ratio | bake s | cache MB |"
        + (
            " ms per edit at {}x{} ({}) |".format(*args.timing_size, ", ".join(choices[0][5]))
            if args.timing_size
            else ""
        ),
        "|---|---|---|---|---|---|---|---|---|" + ("---|" if args.timing_size else ""),
    ]
    for name, choice, result, bake_s, num_bytes, timings in choices:
        lines.append(
            f"| {name} | {choice.components} | {choice.bounces} | {result.point} | {result.predicted_db:.1f} | "
            f"{result.measured_db:.1f} | {result.energy_ratio:.3f} | {bake_s:.0f} | {num_bytes / 1e6:.1f} |"
            + (" " + " / ".join(f"{ms:.0f}" for ms in timings.values()) + " |" if timings else "")
        )
    lines += ["", f"Machine: {machine_description()}; {datetime.date.today().isoformat()}."]
    write_text_atomic(args.out / "summary.md", "\n".join(lines) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
