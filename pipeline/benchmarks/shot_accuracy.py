"""The shot cache against the full frame: accuracy per light edit, and edit timings, per bundled scene.

    python -m pipeline.benchmarks.shot_accuracy SCENE [SCENE ...] --width 320 --height 240 --spp 1024 \
        [--quality 35] [--edits EDIT ...] [--timing-size 640 480] [--repeats 7] --out docs/bench/shot [--work DIR]

SCENE is a bundled scene (`pipeline.scenes.SCENES`) or a layered one (`LAYERED_SCENES`, e.g.
'glossy+dome': the glossy shot baked as it is, relit under a lights layer that adds a lat-long dome,
as a user adds lights to a baked shot). Per scene: the default bake (`pipeline.bake.shot.bake_shot`)
of the bundled scene at the given size, then per light edit (the shot, the scene's example edits and
a new sphere light, all over the layered scene's layer) the relit frame against `relight reference
--max-bounces 8` at `--spp`: PSNR (raw, and corrected for the reference's own noise as the bake's
quality check does, with the reference's noise floor beside it), relMSE, the energy ratio
mean(x) / mean(y), and the indirect part alone (relit minus its direct component, against the full
reference minus the direct-only one) as relMSE and energy ratio. The error is split by pixel class
(`texture_filtering.pixel_classes`): the textured pixels' (albedo and/or normal map) share of the
squared error and their PSNR, and the edge pixels' share.

With `--timing-size W H` the chosen sizes are baked again at that size (no reference) and each kind
of edit is timed (`EDIT_KINDS`: median ms of the edit and the re-render, warm); a kind the scene or
its relighter cannot do is named in words (`NO_DOME`, `NOT_SUPPORTED`), never timed.

Writes shot.csv (one row per scene and edit), scenes.csv (one row per scene: what the bake chose,
its cost and the timings) and summary.md (both tables and the commands) into --out. A run replaces
the rows of the scenes it measured and keeps the others', so one scene can be measured again alone.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import datetime
import io
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pipeline.bake.adapter import cache_bytes
from pipeline.bake.methods import bake_method
from pipeline.bake.quality import QualityResult, corrected_psnr, noise_mse
from pipeline.bake.shot import DEFAULT_TARGET_DB, ShotChoice, bake_shot
from pipeline.benchmarks import run_in_work
from pipeline.benchmarks.bench.measure import machine_description, moved
from pipeline.benchmarks.cuts_sweep import rotated
from pipeline.benchmarks.texture_filtering import CLASSES, pixel_classes
from pipeline.reference.path_tracer import PathTracer, ReferenceImage, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import LAYERED_SCENES, SCENES, layered_edit_layers, light_edit_layers
from pipeline.scenes.lights import NEW_LIGHT_PATH, new_sphere_layer
from pipeline.tracing_bench import median_seconds
from relight_torch import open_cache
from relight_torch.cache.layer import read_cache_layer
from relight_torch.direct.loading import shot_lights
from relight_torch.indirect import IndirectRelighter
from relight_torch.io.atomic import write_text_atomic
from relight_torch.lights.light import LightKind, Shaping
from relight_torch.metrics import psnr_from_mse, rel_mse
from relight_torch.protocol import CacheRelighter

REFERENCE_BOUNCES = 8
EDIT_KINDS = ("colour", "shaping", "move", "new light", "dome turn", "material")
NO_DOME = "no dome"
NOT_SUPPORTED = "not supported"
TEXTURED, EDGE = CLASSES.index("textured"), CLASSES.index("edge")


@dataclasses.dataclass(frozen=True)
class Shot:
    """A measured scene: the bundled scene baked, its camera, and the lights layers it is relit under.

    Attributes:
        name: the scene's name in the tables ('cornell_box', 'glossy+dome').
        base: the bundled scene baked (`SCENES`).
        path: its written .usda.
        camera: its camera prim.
        edits: edit name -> lights layer ('shot' first: None, or the layered scene's layer).
    """

    name: str
    base: str
    path: Path
    camera: str
    edits: dict[str, Path | None]


def shot_of(name: str, work: Path) -> Shot:
    """The scene `name` (bundled or layered) written into `work` with its edit layers and a new light."""
    bundled = SCENES[LAYERED_SCENES[name].base if name in LAYERED_SCENES else name]
    path = bundled.write(work)
    edits: dict[str, Path | None] = (
        layered_edit_layers(name, work) if name in LAYERED_SCENES else light_edit_layers(name, work)
    )
    new_light = new_sphere_layer(path, bundled.camera, work / f"{name}.lights.new_light.usda", over=edits["shot"])
    return Shot(name, bundled.name, path, bundled.camera, edits | {"new_light": new_light})


@dataclasses.dataclass(frozen=True)
class EditRow:
    """One edit's figures against the full frame (see the module doc)."""

    scene: str
    edit: str
    width: int
    height: int
    spp: int
    psnr_db: float
    corrected_psnr_db: float
    reference_floor_db: float
    rel_mse: float
    energy_ratio: float
    indirect_rel_mse: float
    indirect_energy_ratio: float
    textured_pixel_share: float
    textured_error_share: float
    textured_psnr_db: float
    edge_error_share: float


@dataclasses.dataclass(frozen=True)
class SceneRow:
    """What the default bake chose for one scene, its cost, and the edit timings (ms, or words)."""

    scene: str
    width: int
    height: int
    components: str
    bounces: int
    sizes: str
    pilot_db: float
    measured_db: float
    energy_ratio: float
    bake_s: float
    cache_mb: float
    timing_size: str
    colour_ms: str
    shaping_ms: str
    move_ms: str
    new_light_ms: str
    dome_turn_ms: str
    material_ms: str
    command: str


def _reference(
    shot: Shot, edit: str, width: int, height: int, bounces: int, spp: int, directory: Path
) -> ReferenceImage:
    """The path tracer's image of `shot` under `edit`, kept as .npz (mean, variance) in `directory`."""
    path = directory / f"reference-{shot.name}-{edit}-{width}x{height}-b{bounces}-{spp}spp.npz"
    if not path.exists():
        scene = load_scene(shot.path, lights_layer=shot.edits[edit], width=width, height=height)
        image = PathTracer(scene, ReferenceSettings(spp=spp, max_bounces=bounces)).render(
            find_camera(scene, shot.camera)
        )
        temporary = path.with_suffix(".part.npz")
        np.savez(temporary, mean=image.mean, variance=image.variance, seconds=image.seconds)
        temporary.replace(path)
    with np.load(path) as stored:
        return ReferenceImage(stored["mean"], stored["variance"], float(stored["seconds"]), width * height * spp)


def _indirect_image(relighter: CacheRelighter, components: str, layer: Path, image: np.ndarray) -> np.ndarray:
    """(H, W, 3) the indirect part of a shot cache's render: none for a 'direct' shot, the indirect
    relighter's own for 'direct+transfer' (`shotComponents`, `pipeline.bake.shot`)."""
    if components == "direct":
        return np.zeros_like(image)
    if not isinstance(relighter, IndirectRelighter):
        raise TypeError(f"{layer}: shotComponents {components!r}, but its relighter is a {type(relighter).__name__}")
    return relighter.indirect_image().numpy()


def error_split(image: np.ndarray, reference: np.ndarray, classes: np.ndarray) -> tuple[float, float, float, float]:
    """(textured pixels' share of the image, their share of the squared error, their PSNR (nan
    without any), the edge pixels' share of the error) of `image` (H, W, 3) against `reference`,
    measured as `relight_torch.metrics.psnr` does; `classes` (H, W) from `pixel_classes`."""
    error = np.mean((np.clip(image, 0.0, 1.0) - np.clip(reference, 0.0, 1.0)) ** 2, axis=-1)
    total = max(float(error.sum()), 1e-30)
    textured = classes == TEXTURED
    textured_db = psnr_from_mse(float(error[textured].mean())) if textured.any() else math.nan
    return (
        float(textured.mean()),
        float(error[textured].sum()) / total,
        textured_db,
        float(error[classes == EDGE].sum()) / total,
    )


def accuracy_rows(shot: Shot, layer: Path, width: int, height: int, spp: int, directory: Path) -> list[EditRow]:
    """One EditRow per edit of `shot` relit from its shot cache `layer` (see the module doc)."""
    description = read_cache_layer(layer)
    relighter = open_cache(layer)
    components = str(description.parameters["shotComponents"])
    scene = load_scene(shot.path, width=width, height=height)
    classes = pixel_classes(scene, find_camera(scene, shot.camera))
    rows = []
    for edit, lights_layer in shot.edits.items():
        relighter.set_lights(shot_lights(description, lights_layer))
        image = relighter.render().numpy()
        indirect = _indirect_image(relighter, components, layer, image)
        full = _reference(shot, edit, width, height, REFERENCE_BOUNCES, spp, directory)
        zero = _reference(shot, edit, width, height, 0, spp, directory)
        reference_indirect = full.mean - zero.mean
        corrected_db, raw_db = corrected_psnr(image, full)
        rows.append(
            EditRow(
                shot.name,
                edit,
                width,
                height,
                spp,
                raw_db,
                corrected_db,
                psnr_from_mse(noise_mse(full)),
                rel_mse(image, full.mean),
                float(image.mean() / full.mean.mean()),
                rel_mse(indirect, reference_indirect),
                float(indirect.mean() / max(float(reference_indirect.mean()), 1e-12)),
                *error_split(image, full.mean, classes),
            )
        )
    return rows


def edit_timings(layer: Path, shot: Shot, repeats: int) -> dict[str, float | str]:
    """Per `EDIT_KINDS` kind, the median ms of the edit and the re-render on a warm relighter of
    `layer` under the shot's lights, or why the kind cannot be timed (`NO_DOME`, `NOT_SUPPORTED`)."""
    description = read_cache_layer(layer)
    relighter = open_cache(layer)
    lights = shot_lights(description, shot.edits["shot"])
    relighter.set_lights(lights)
    relighter.render()
    first = lights[0]
    dome = next((light for light in lights if light.kind is LightKind.DOME), None)
    added = next(light for light in shot_lights(description, shot.edits["new_light"]) if light.path == NEW_LIGHT_PATH)
    toggles = iter(range(1 << 30))

    def timed(edit: Callable[[int], None]) -> float:
        def run() -> None:
            edit(next(toggles) % 2)
            relighter.render()

        return 1e3 * median_seconds(run, repeats)

    colours = (first, dataclasses.replace(first, color=(first.color[0], 0.8 * first.color[1], 0.6 * first.color[2])))
    shaping = first.shaping or Shaping()
    shaped = (first, dataclasses.replace(first, shaping=dataclasses.replace(shaping, focus=shaping.focus + 2.0)))
    timings: dict[str, float | str] = {
        "colour": timed(lambda k: relighter.set_light(colours[k])),
        "shaping": timed(lambda k: relighter.set_light(shaped[k])),
        "move": timed(lambda k: relighter.set_light(moved(first, 0.01 * (1 + k)))),
        "new light": timed(lambda k: relighter.set_light(added) if k == 0 else relighter.remove_light(added.path)),
        "dome turn": NO_DOME if dome is None else timed(lambda k: relighter.set_light(rotated(dome, 2.0 * (1 + k)))),
        # UsdPreviewSurface roughness of the first material (`CacheRelighter.edit_material`).
        "material": (
            timed(lambda k: relighter.edit_material(0, roughness=0.3 + 0.2 * k))
            if relighter.material_edits
            else NOT_SUPPORTED
        ),
    }
    relighter.set_lights(lights)
    return timings


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", nargs="+", choices=sorted(SCENES) + sorted(LAYERED_SCENES))
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--spp", type=int, default=1024)
    parser.add_argument("--quality", type=float, default=DEFAULT_TARGET_DB)
    parser.add_argument("--edits", nargs="+", metavar="EDIT", help="measure only these edits (default: all)")
    parser.add_argument("--timing-size", type=int, nargs=2, metavar=("W", "H"))
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument(
        "--work",
        type=Path,
        help="where bakes and references go, references kept between runs (default: a temporary directory, removed)",
    )
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    return run_in_work(args.work, lambda work: _run(args, work))


def _command(args: argparse.Namespace, scenes: list[str]) -> str:
    """The command line that measures `scenes` as `args` did."""
    return (
        f"python -m pipeline.benchmarks.shot_accuracy {' '.join(scenes)} --width {args.width} "
        f"--height {args.height} --spp {args.spp} --quality {args.quality:g}"
        + (f" --edits {' '.join(args.edits)}" if args.edits else "")
        + (f" --timing-size {args.timing_size[0]} {args.timing_size[1]}" if args.timing_size else "")
        + f" --repeats {args.repeats} --out {args.out}"
    )


def _run(args: argparse.Namespace, work: Path) -> int:
    """Measure every scene of `args` with its bakes and references in `work`; write the tables."""
    work.mkdir(parents=True, exist_ok=True)
    rows, scene_rows = [], []
    bakes: dict[str, tuple[ShotChoice, QualityResult, float]] = {}  # per bundled scene: one bake serves its layers
    for name in args.scenes:
        shot = shot_of(name, work)
        if args.edits:
            shot = dataclasses.replace(shot, edits={e: p for e, p in shot.edits.items() if e in args.edits})
        if shot.base not in bakes:
            scene = load_scene(shot.path, width=args.width, height=args.height)
            start = time.perf_counter()
            choice, result = bake_shot(
                scene, find_camera(scene, shot.camera), work / f"{shot.base}-cache", shot.base, args.quality
            )
            bakes[shot.base] = (choice, result, time.perf_counter() - start)
        choice, result, bake_s = bakes[shot.base]
        rows += accuracy_rows(shot, result.layer, args.width, args.height, args.spp, work)
        timings: dict[str, float | str] = {}
        if args.timing_size:
            big = load_scene(shot.path, width=args.timing_size[0], height=args.timing_size[1])
            method = "direct" if choice.components == "direct" else "transfer"
            big_layer = bake_method(method).adapter.bake(
                big, find_camera(big, shot.camera), work / f"{shot.base}-timing", shot.base, result.point, 1, 2
            )
            timings = edit_timings(big_layer, shot, args.repeats)
        scene_rows.append(
            SceneRow(
                name,
                args.width,
                args.height,
                choice.components,
                choice.bounces,
                str(result.point),
                result.predicted_db,
                result.measured_db,
                result.energy_ratio,
                bake_s,
                cache_bytes(result.layer) / 1e6,
                "{}x{}".format(*args.timing_size) if args.timing_size else "",
                *(_ms(timings.get(kind)) for kind in EDIT_KINDS),
                _command(args, [name]),
            )
        )
    _write(args.out, rows, scene_rows, _command(args, args.scenes))
    return 0


def _ms(value: float | str | None) -> str:
    """A timing cell: ms rounded, the reason it is not timed, or empty when timings were not asked for."""
    return "" if value is None else value if isinstance(value, str) else f"{value:.0f}"


def _merged(path: Path, row_type: type, new_rows: list) -> list:
    """The rows of `path` (a CSV of `row_type`'s fields) whose scene `new_rows` do not measure, then
    `new_rows`; an older file with other columns is replaced whole."""
    readers = {
        field.name: {"int": int, "float": float}.get(str(field.type), str) for field in dataclasses.fields(row_type)
    }
    if not path.exists():
        return new_rows
    with open(path, newline="") as handle:
        reader = csv.DictReader(handle)
        if reader.fieldnames != list(readers):
            return new_rows
        measured = {row.scene for row in new_rows}
        kept = [
            row_type(**{name: read(row[name]) for name, read in readers.items()})
            for row in reader
            if row["scene"] not in measured
        ]
    return kept + new_rows


def _write_csv(path: Path, row_type: type, rows: list) -> None:
    """`rows` (of `row_type`) as CSV with a header of its field names, written atomically."""
    fields = [field.name for field in dataclasses.fields(row_type)]
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(fields)
    writer.writerows([[getattr(row, field) for field in fields] for row in rows])
    write_text_atomic(path, text.getvalue())


def _cell(value: float, spec: str) -> str:
    """`value` formatted, or 'not measured' for nan (a row measured before the column existed)."""
    return "not measured" if math.isnan(value) else format(value, spec)


def _write(out: Path, new_rows: list[EditRow], new_scene_rows: list[SceneRow], command: str) -> None:
    """shot.csv, scenes.csv and summary.md in `out`, the rows of scenes not measured now kept."""
    rows = _merged(out / "shot.csv", EditRow, new_rows)
    scene_rows = _merged(out / "scenes.csv", SceneRow, new_scene_rows)
    _write_csv(out / "shot.csv", EditRow, rows)
    _write_csv(out / "scenes.csv", SceneRow, scene_rows)
    lines = [
        "# The shot cache against the full frame",
        "",
        f"Generated by `python -m pipeline.benchmarks.shot_accuracy SCENE ...` (module "
        "`pipeline.benchmarks.shot_accuracy`); a run replaces its scenes' rows and keeps the others'. "
        f"The last run: `{command}`; each scene's own command is listed below the tables.",
        "",
        f"Accuracy against the path tracer ({REFERENCE_BOUNCES} bounces) at each row's size and samples per "
        "pixel. PSNR is raw; 'corrected' subtracts the reference's own noise (the bake's quality check), whose "
        "floor is given: a PSNR near the floor says the reference cannot tell more. The indirect part is the relit "
        "frame less its direct component against the full reference less the direct-only one. 'textured' pixels "
        "read a texture (albedo and/or normal map), 'edge' pixels see more than one object; their error share is "
        "of the image's squared error.",
        "",
        "| scene | edit | size | spp | PSNR dB | corrected dB | floor dB | relMSE | energy ratio | indirect relMSE "
        "| indirect energy ratio | textured pixels | textured error share | textured PSNR dB | edge error share |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {r.scene} | {r.edit} | {r.width}x{r.height} | {r.spp} | {r.psnr_db:.2f} | "
        f"{_cell(r.corrected_psnr_db, '.2f')} | {_cell(r.reference_floor_db, '.1f')} | {r.rel_mse:.4f} | "
        f"{r.energy_ratio:.3f} | {r.indirect_rel_mse:.4f} | {r.indirect_energy_ratio:.3f} | "
        f"{_cell(r.textured_pixel_share, '.0%')} | "
        + (
            f"{r.textured_error_share:.0%} | {r.textured_psnr_db:.2f}"
            if r.textured_pixel_share > 0
            else "none | none"
            if r.textured_pixel_share == 0
            else "not measured | not measured"
        )
        + f" | {_cell(r.edge_error_share, '.0%')} |"
        for r in rows
    ]
    lines += [
        "",
        "Per scene: what the default bake chose (pilot and measured PSNR against the full frame at the bake's "
        "size), its time and cache size, and the median ms of each kind of edit plus the re-render at the timing "
        f"size ({', '.join(EDIT_KINDS)}); '{NO_DOME}': the scene has no dome light; '{NOT_SUPPORTED}': the shot "
        "cache's relighter does not edit materials (its transport was baked with them).",
        "",
        "| scene | size | components | bounces | sizes | pilot dB | measured dB | energy ratio | bake s | cache MB "
        "| timing size | " + " | ".join(f"{kind} ms" for kind in EDIT_KINDS) + " |",
        "|---|---|---|---|---|---|---|---|---|---|---|" + "---|" * len(EDIT_KINDS),
    ]
    for r in scene_rows:
        timings = (r.colour_ms, r.shaping_ms, r.move_ms, r.new_light_ms, r.dome_turn_ms, r.material_ms)
        lines.append(
            f"| {r.scene} | {r.width}x{r.height} | {r.components} | {r.bounces} | {r.sizes} | {r.pilot_db:.1f} | "
            f"{r.measured_db:.1f} | {r.energy_ratio:.3f} | {r.bake_s:.0f} | {r.cache_mb:.1f} | "
            f"{r.timing_size or 'not timed'} | " + " | ".join(t or "not timed" for t in timings) + " |"
        )
    lines += ["", "Commands:", ""] + [f"- {r.scene}: `{r.command}`" for r in scene_rows]
    lines += ["", f"Machine: {machine_description()}; {datetime.date.today().isoformat()}."]
    write_text_atomic(out / "summary.md", "\n".join(lines) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
