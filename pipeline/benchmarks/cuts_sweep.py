"""Sweep of the cuts method (Cheslack-Postava et al. 2008, environment mode): lights x sigma x illumination cut size.

    python -m pipeline.benchmarks.cuts_sweep [SCENE...] --width W --height H [--lights 1024 4096 ...]
        [--sigmas 1.5 2 3] [--cut-sizes 128 256 512] [--betas 1 0.5] [--mode env|indirect]
        [--spp N] [--repeats R] [--csv FILE] [--out DIR [--reuse]]

Per scene, light count, sigma and tree blend beta (1 = geometric tree, < 1 data-driven) it bakes
once (bake_s, cache_bytes: that bake's payloads) and relights with every illumination cut size,
under the shot's lights and every example light edit, against `PathTracer(max_bounces=0)` (PSNR,
relMSE; indirect mode: `max_bounces=1`, and psnr_indirect_db against its 1-bounce minus 0-bounce
part). relight_ms is the median of the first light moved and re-rendered
(`pipeline.benchmarks.bench.measure.relight_ms`; env mode: a dome translated, whose light does not
change: its illumination cut is made again, nothing else of the cuts' light; see `edit_timings` for
edits that change more). params also record what the cost follows: `vis` = mean visibility cut size
per lattice vertex, and per sub-sample `inputs` = visibility cut entries merged (its three
vertices'), `merged` = merged-cut entries shaded or tested and `dark` = dark visibility clusters
dropped before the illumination cut is merged in, so relight_ms can be read against the cut sizes at
different light counts. One CSV row per (scene, lights, sigma, cut size, light edit), the columns
shared with the other methods' sweeps (`pipeline.benchmarks.rows`).

With `--timing` only the shot's lights are relit (no references: PSNR columns NaN): for the 640 x
480, cut size 256 figure of the issue, one row per kind of edit (`edit_timings`: the dome moved,
turned, a material's colour, its roughness, a small object's roughness; params add `cpu_ms`, the
median CPU time, and `evaluated`, the merged entries per sub-sample whose BRDF factors the edit
recomputed, and `kept_mb`, `CutsRelighter.kept_bytes`; with `--compiled` also `warmup_cpu_s`, one
round of every edit run first, which compiles the variants the edits use). With `--cost` (implies
--timing) the bakes are timed round-robin instead, `--repeats` rounds of the cuts' light fully
evaluated per bake, so that a shared machine's load changes affect every bake alike: for reading
relight_ms against `merged` as the number of point lights grows (Cheslack-Postava et al. 2008: the
cost follows the merged cut size, not the lights).

With `--reuse` the caches already baked in `--out` with the same size and bake parameters are
relit instead of baked again (bake_s NaN): for timing relighter changes at 640 x 480.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from pipeline.bake.adapter import cache_bytes, format_params
from pipeline.bake.cuts.bake import CutsSettings, bake_cuts
from pipeline.benchmarks.bench.measure import device_name, moved, relight_ms
from pipeline.benchmarks.bench.references import References
from pipeline.benchmarks.reuse import reusable_bake
from pipeline.benchmarks.rows import COLUMNS, NAN, SweepRow, csv_line, write_csv
from pipeline.benchmarks.stopwatch import Stopwatch
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES, light_edit_layers
from relight_torch.cache.layer import read_cache_layer
from relight_torch.cuts.open import open_cuts_relighter
from relight_torch.cuts.relighter import CutsRelighter, CutsRelightSettings
from relight_torch.direct.loading import shot_lights
from relight_torch.lights.light import Light, LightKind
from relight_torch.metrics import psnr, rel_mse


def rotated(light: Light, degrees: float) -> Light:
    """`light` turned by `degrees` about world +Y (a dome edit that changes the illumination cut)."""
    cos, sin = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    turn = np.array([[cos, 0.0, sin, 0.0], [0.0, 1.0, 0.0, 0.0], [-sin, 0.0, cos, 0.0], [0.0, 0.0, 0.0, 1.0]])
    return dataclasses.replace(light, world_from_light=turn @ light.world_from_light)


def edit_timings(relighter: CutsRelighter, repeats: int) -> dict[str, tuple[float, float, float]]:
    """Per kind of edit, (median wall ms, median CPU ms, merged entries per sub-sample whose BRDF
    factors were recomputed) of `repeats` edits each followed by `render()`.

    Kinds: 'move' (the first dome translated, as `measure.relight_ms`: its light and illumination
    cut are unchanged), 'rotate' (the dome turned 2 or 4 degrees about +Y: the illumination cut
    changes), 'colour' (a material's diffuse colour), 'roughness' (its roughness, 0.3 or 0.6),
    both on the material with the second most sub-samples (`dome`: the backdrop, 43 %), and
    'roughness_object' on the third least common one (`dome`: the red plastic, 2 %). Lights and
    materials are restored after.
    """
    lights, params = relighter.lights, relighter.params
    dome = next(light for light in lights if light.kind is LightKind.DOME)
    order = torch.bincount(relighter.direct.gbuffer.material_id.long()).argsort(descending=True).tolist()
    large, small = order[1], order[-3]
    edits = {
        "move": lambda i: relighter.set_light(moved(dome, 0.01 * (1 + i % 2))),
        "rotate": lambda i: relighter.set_light(rotated(dome, 2.0 * (1 + i % 2))),
        "colour": lambda i: relighter.edit_material(large, diffuse_color=((0.1, 0.5, 0.15), (0.5, 0.1, 0.1))[i % 2]),
        "roughness": lambda i: relighter.edit_material(large, roughness=(0.3, 0.6)[i % 2]),
        "roughness_object": lambda i: relighter.edit_material(small, roughness=(0.3, 0.6)[i % 2]),
    }
    timings = {}
    num_samples = relighter.cuts.sample_vertices.shape[0]
    for kind, edit in edits.items():
        relighter.render()
        watch, evaluated = Stopwatch(), []
        for index in range(repeats):
            edit(index)
            with watch.section():
                relighter.render()
            evaluated.append(relighter.stats["evaluated"] / num_samples)
        timings[kind] = (*watch.median_ms(), statistics.median(evaluated))
        relighter.set_lights(lights)
        relighter.set_params(params)
    return timings


def cut_rows(
    relighter: CutsRelighter,
    layer: Path,
    scene_name: str,
    args: argparse.Namespace,
    parameters: dict[str, object],
    bake_s: float,
    expected: dict | None,
    layers: dict[str, Path | None],
) -> list[SweepRow]:
    """Rows of one bake, one per (cut size, light edit)."""
    description = read_cache_layer(layer)
    num_bytes = float(cache_bytes(layer))
    num_samples = relighter.cuts.sample_vertices.shape[0]
    mean_vis = float(relighter.cuts.visibility.sizes().double().mean())
    rows = []
    for cut_size in args.cut_sizes:
        relighter.set_settings(CutsRelightSettings(max_cut=cut_size, compiled=args.compiled))
        for edit, lights_layer in layers.items():
            relighter.set_lights(shot_lights(description, lights_layer))
            image = relighter.render().cpu().numpy()
            stats = dict(relighter.stats)
            params = {
                **parameters,
                "cut": cut_size,
                "vis": f"{mean_vis:.1f}",
                "inputs": f"{stats['inputs'] / num_samples:.1f}",
                "merged": f"{stats['merged'] / num_samples:.1f}",
                "dark": f"{stats['dark'] / num_samples:.1f}",
            }
            if args.timing:
                if args.compiled:  # one round of every edit first: compiles the variants they use
                    start = time.process_time()
                    edit_timings(relighter, 1)
                    params["warmup_cpu_s"] = f"{time.process_time() - start:.1f}"
                for kind, (wall, cpu, evaluated) in edit_timings(relighter, args.repeats).items():
                    row = SweepRow(
                        "cuts",
                        scene_name,
                        args.width,
                        args.height,
                        kind,
                        format_params(
                            {
                                **params,
                                "cpu_ms": f"{cpu:.1f}",
                                "evaluated": f"{evaluated:.1f}",
                                "kept_mb": f"{relighter.kept_bytes() / 2**20:.0f}",
                            }
                        ),
                        NAN,
                        NAN,
                        NAN,
                        num_bytes,
                        bake_s,
                        wall,
                        device_name("cpu"),
                    )
                    print(csv_line(row), file=sys.stderr, flush=True)
                    rows.append(row)
                continue
            timing = relight_ms(relighter, args.repeats) if edit == "shot" else NAN
            params = format_params(params)
            quality = (NAN, NAN, NAN)
            if expected is not None:
                full, indirect = expected[edit]
                quality = (
                    psnr(image, full),
                    NAN if indirect is None else psnr(relighter.indirect_image().cpu().numpy(), indirect),
                    rel_mse(image, full),
                )
            row = SweepRow(
                "cuts",
                scene_name,
                args.width,
                args.height,
                edit,
                params,
                *quality,
                num_bytes,
                bake_s,
                timing,
                device_name("cpu"),
            )
            print(
                f"{row.method},{row.scene},{row.light_edit},{row.params},psnr={row.psnr_db:.2f},"
                f"bytes={num_bytes:.0f},bake_s={bake_s:.1f},relight_ms={timing:.1f}",
                file=sys.stderr,
                flush=True,
            )
            rows.append(row)
    return rows


def cost_rows(
    bakes: list[tuple[CutsRelighter, Path, dict[str, object], float]], scene_name: str, args: argparse.Namespace
) -> list[SweepRow]:
    """One row per bake (first cut size, the shot's lights), relight_ms timed round-robin: the
    cuts' light with every merged entry evaluated (`cut_samples` of copies of the lights, so that
    no kept columns serve: as after an edit that changes the whole illumination cut); params add
    `cpu_ms`."""
    cut_size = args.cut_sizes[0]
    watches = [Stopwatch() for _ in bakes]
    for relighter, _, _, _ in bakes:
        relighter.set_settings(CutsRelightSettings(max_cut=cut_size, compiled=args.compiled))
        relighter.render()
    for _ in range(args.repeats):
        for watch, (relighter, _, _, _) in zip(watches, bakes, strict=True):
            with watch.section():
                relighter.cut_samples([dataclasses.replace(light) for light in relighter.lights])  # not the kept lights
    rows = []
    for watch, (relighter, layer, parameters, bake_s) in zip(watches, bakes, strict=True):
        num_samples = relighter.cuts.sample_vertices.shape[0]
        wall_ms, cpu_ms = watch.median_ms()
        params = format_params(
            {
                **parameters,
                "cut": cut_size,
                "cpu_ms": f"{cpu_ms:.1f}",
                "vis": f"{float(relighter.cuts.visibility.sizes().double().mean()):.1f}",
                "inputs": f"{relighter.stats['inputs'] / num_samples:.1f}",
                "merged": f"{relighter.stats['merged'] / num_samples:.1f}",
                "dark": f"{relighter.stats['dark'] / num_samples:.1f}",
            }
        )
        rows.append(
            SweepRow(
                "cuts",
                scene_name,
                args.width,
                args.height,
                "shot",
                params,
                NAN,
                NAN,
                NAN,
                float(cache_bytes(layer)),
                bake_s,
                wall_ms,
                device_name("cpu"),
            )
        )
        print(csv_line(rows[-1]), file=sys.stderr, flush=True)
    return rows


def sweep_scene(name: str, args: argparse.Namespace, directory: Path) -> list[SweepRow]:
    """Every (lights, sigma) bake of one scene and its rows."""
    bundled = SCENES[name]
    shot = bundled.write(directory)
    layers = {"shot": None} if args.timing else light_edit_layers(name, directory)
    bounces = int(args.mode == "indirect")
    refs = References(shot, bundled.camera, args.width, args.height, layers, args.spp, directory / "references")
    expected = (
        None
        if args.timing
        else {edit: (refs.full(edit, bounces), refs.indirect(edit, bounces) if bounces else None) for edit in layers}
    )
    scene = load_scene(shot, width=args.width, height=args.height)
    camera = find_camera(scene, bundled.camera)
    rows, bakes = [], []
    for num_lights, sigma, beta in itertools.product(args.lights, args.sigmas, args.betas):
        settings = CutsSettings(
            mode=args.mode, num_lights=num_lights, sigma=sigma, lattice_edge=args.lattice_edge, beta=beta
        )
        cache_dir = directory / f"cache-{num_lights}-{sigma}-{beta}"
        layer = (
            reusable_bake(
                cache_dir / f"{name}.relight.usda",
                "cuts",
                (args.width, args.height),
                args.supersampling,
                {**settings.parameters(), "textureSamples": args.texture_samples},
            )
            if args.reuse
            else None
        )
        bake_s = NAN
        if layer is None:
            start = time.perf_counter()
            layer = bake_cuts(
                scene, camera, cache_dir, name, args.supersampling, args.texture_samples, settings=settings
            )
            bake_s = time.perf_counter() - start
        relighter = open_cuts_relighter(layer)
        parameters = {
            "mode": settings.mode,
            "lights": num_lights,
            "sigma": sigma,
            "beta": beta,
            "latticeEdge": f"{args.lattice_edge:.4g}",
            "supersampling": args.supersampling,
        }
        if args.cost:
            bakes.append((relighter, layer, parameters, bake_s))
        else:
            rows += cut_rows(relighter, layer, name, args, parameters, bake_s, expected, layers)
    return cost_rows(bakes, name, args) if args.cost else rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", nargs="*", default=["dome"], choices=sorted(SCENES))
    parser.add_argument("--width", type=int, default=64)
    parser.add_argument("--height", type=int, default=48)
    parser.add_argument("--lights", type=int, nargs="+", default=[4096])
    parser.add_argument("--sigmas", type=float, nargs="+", default=[1.5, 2.0, 3.0])
    parser.add_argument("--cut-sizes", type=int, nargs="+", default=[128, 256, 512])
    parser.add_argument("--betas", type=float, nargs="+", default=[1.0])
    parser.add_argument("--mode", choices=("env", "indirect"), default="env")
    parser.add_argument("--lattice-edge", type=float, default=CutsSettings().lattice_edge)
    parser.add_argument("--supersampling", type=int, default=2)
    parser.add_argument("--texture-samples", type=int, default=2)
    parser.add_argument("--spp", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--timing", action="store_true", help="relight the shot's lights only, no references")
    parser.add_argument(
        "--compiled",
        action="store_true",
        help="CutsRelightSettings(compiled=True): the BRDF blocks through torch.compile",
    )
    parser.add_argument("--cost", action="store_true", help="time the bakes round-robin (implies --timing)")
    parser.add_argument("--out", type=Path, help="working directory (default: a temporary one)")
    parser.add_argument(
        "--reuse",
        action="store_true",
        help="relight the caches an earlier run baked in --out with the same size and bake "
        "parameters instead of baking again (bake_s NaN)",
    )
    parser.add_argument("--csv", type=Path, help="write the rows here (default: stdout)")
    args = parser.parse_args(argv)
    args.timing |= args.cost
    with tempfile.TemporaryDirectory() as temporary:
        directory = args.out or Path(temporary)
        rows = [row for name in args.scenes for row in sweep_scene(name, args, directory / name)]
    if args.csv:
        write_csv(rows, args.csv)
    else:
        print(",".join(COLUMNS), *map(csv_line, rows), sep="\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
