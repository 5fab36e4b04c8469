"""Sweep of the clustered-gather method: clusters per representative x view representatives x the
shared-point grid, against the one-bounce reference.

    python -m pipeline.benchmarks.gather_sweep SCENE [SCENE...] --width W --height H
        [--clusters 15 30 60 120 240] [--representatives 0 ...] [--point-cells 64 ...]
        [--directions N] [--gather-samples S ...] [--spp N] [--shadows embree|shadowmaps]
        [--shadow-map-resolution R] [--out DIR] [--csv FILE]
    python -m pipeline.benchmarks.gather_sweep SCENE --timing --width 400 --height 400 [...]

Per scene and (clusters, representatives, point cells) it bakes once (bake_s) and relights the cache
under the shot's lights and every example light edit (`pipeline.scenes.write_light_edits`), once per
`--gather-samples` count, comparing with `PathTracer(max_bounces=1)`: psnr_db on the full image,
psnr_indirect_db on the indirect part against the reference's 1-bounce minus 0-bounce image
(references are kept on disk under OUT and re-used, `bench.references`). cache_bytes counts every
payload of the layer (the direct part included); relight_ms is the median time of re-rendering
(direct + indirect) after a light move (`bench.measure.relight_ms`, as in `relight bench`).
Representatives 0 means the default (40,000 at 400 x 400, scaled with the pixel count). One CSV row
per (scene, setting, edit), in the columns every method's sweep shares (`pipeline.benchmarks.rows`).

With `--timing` it bakes one cache per scene with the first value of each setting (or, with
`--reuse`, relights the one already in OUT) and prints the median ms of each kind of edit
(`edit_timings`, wall or `--cpu-time`) with both visibilities and every gather-sample count (with
shadow maps also the mean CPU ms of a move's map build and lookups), the cache bytes, the bake
seconds and the process's peak resident memory (`resource.getrusage`: the bake's peak when it
baked).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import resource
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from pipeline.bake.adapter import cache_bytes, format_params
from pipeline.bake.gather.bake import GatherSettings, bake_gather
from pipeline.benchmarks.bench.measure import moved, relight_ms
from pipeline.benchmarks.bench.references import References
from pipeline.benchmarks.rows import COLUMNS, SweepRow, csv_line, write_csv
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES, light_edit_layers
from relight_torch.cache.layer import read_cache_layer
from relight_torch.direct.loading import shot_lights
from relight_torch.direct.settings import RelightSettings
from relight_torch.gather.open import open_gather_relighter
from relight_torch.gather.relighter import DEFAULT_GATHER_SAMPLES, GatherRelighter
from relight_torch.lights.light import Shaping
from relight_torch.metrics import psnr, rel_mse


def _median_ms(
    relighter: GatherRelighter, edits: list, repeats: int, clock: Callable[[], float]
) -> tuple[float, float]:
    """Median ms of `set_light(edit)` + `render()` over `repeats` edits cycled from `edits`, and of
    its indirect part alone (`render()` is the direct image plus `indirect_image()`, timed apart:
    the direct part builds the light's shadow maps, which the gathers then share)."""
    full, indirect = [], []
    for edit in itertools.islice(itertools.cycle(edits), repeats):
        start = clock()
        relighter.set_light(edit)
        relighter.direct.render()
        middle = clock()
        relighter.indirect_image()
        end = clock()
        full.append(1e3 * (end - start))
        indirect.append(1e3 * (end - middle))
    return statistics.median(full), statistics.median(indirect)


def edit_timings(
    relighter: GatherRelighter, repeats: int = 5, clock: Callable[[], float] = time.perf_counter
) -> dict[str, tuple[float, float]]:
    """Median ms of a full re-render (direct + indirect), and of its indirect part, after each kind
    of edit of the first light.

    'colour': intensity and colour; 'shaping': ShapingAPI focus (no new shadow rays); 'move': a
    translation (the light's direct transport and its gathers' light recomputed). The rig is
    restored afterwards. `clock`: wall time, or `time.process_time` for this process's CPU time
    (on a shared machine, what a single-threaded run would take alone).
    """
    lights = relighter.lights
    light = lights[0]
    relighter.render()
    shaping = light.shaping or Shaping()
    timings = {
        "colour": _median_ms(
            relighter,
            [dataclasses.replace(light, intensity=light.intensity * f, color=(1.0, f, 0.5)) for f in (0.5, 0.75)],
            repeats,
            clock,
        ),
        "shaping": _median_ms(
            relighter,
            [dataclasses.replace(light, shaping=dataclasses.replace(shaping, focus=f)) for f in (1.0, 2.0)],
            repeats,
            clock,
        ),
        "move": _median_ms(relighter, [moved(light, 0.01 * (1 + i % 2)) for i in range(repeats)], repeats, clock),
    }
    relighter.set_lights(lights)
    return timings


def _bake(name: str, args: argparse.Namespace, directory: Path, settings: GatherSettings) -> tuple[Path, float]:
    bundled = SCENES[name]
    scene = load_scene(directory / f"{name}.usda", width=args.width, height=args.height)
    start = time.perf_counter()
    layer = bake_gather(
        scene,
        find_camera(scene, bundled.camera),
        directory / "cache",
        name,
        args.supersampling,
        args.texture_samples,
        settings=settings,
        progress=False,
    )
    return layer, time.perf_counter() - start


def _settings(args: argparse.Namespace, clusters: int, representatives: int, point_cells: int) -> GatherSettings:
    return GatherSettings(
        num_directions=args.directions,
        num_clusters=clusters,
        num_representatives=representatives or None,
        point_cells=point_cells,
    )


def _relight_settings(args: argparse.Namespace) -> RelightSettings:
    return RelightSettings(shadow_map_resolution=args.shadow_map_resolution)


def sweep_scene(name: str, args: argparse.Namespace, directory: Path) -> list[SweepRow]:
    """The sweep's rows of one scene (printed as CSV lines as they are measured)."""
    shot = SCENES[name].write(directory)
    layers = light_edit_layers(name, directory)
    expected = References(
        shot, SCENES[name].camera, args.width, args.height, layers, args.spp, directory / "references"
    )
    rows = []
    for clusters, representatives, point_cells in itertools.product(
        args.clusters, args.representatives, args.point_cells
    ):
        settings = _settings(args, clusters, representatives, point_cells)
        layer, bake_s = _bake(name, args, directory, settings)
        num_bytes = cache_bytes(layer)
        for gather_samples in args.gather_samples:
            relighter = open_gather_relighter(
                layer, shadows=args.shadows, settings=_relight_settings(args), gather_samples=gather_samples
            )
            params = format_params(
                {
                    **settings.parameters(),
                    "gatherSamples": gather_samples,
                    "numRepresentatives": sum(s.num_representatives for s in relighter.sets.values()),
                    "surfacePoints": relighter.points.num_points,
                    "shadows": args.shadows,
                }
            )
            move_ms = relight_ms(relighter, args.repeats)
            for edit, layer_path in layers.items():
                relighter.set_lights(shot_lights(relighter.direct.description, layer_path))
                image, indirect = relighter.render().numpy(), relighter.indirect_image().numpy()
                full = expected.full(edit, 1)
                row = SweepRow(
                    "gather",
                    name,
                    args.width,
                    args.height,
                    edit,
                    params,
                    psnr(image, full),
                    psnr(indirect, expected.indirect(edit, 1)),
                    rel_mse(image, full),
                    num_bytes,
                    bake_s,
                    move_ms,
                )
                print(csv_line(row), flush=True)
                rows.append(row)
    return rows


def time_scene(name: str, args: argparse.Namespace, directory: Path) -> None:
    """Print the edit timings of one default-sized cache with both visibilities."""
    settings = _settings(args, args.clusters[0], args.representatives[0], args.point_cells[0])
    layer, bake_s = directory / "cache" / f"{name}.relight.usda", float("nan")
    if not (args.reuse and layer.is_file()):
        SCENES[name].write(directory)
        layer, bake_s = _bake(name, args, directory, settings)
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    description = read_cache_layer(layer)
    params = format_params({key: description.parameters[key] for key in settings.parameters()})
    print(
        f"{name} {args.width}x{args.height} {params}: bake {bake_s:.1f} s, peak RSS {peak_mib:.0f} MiB, "
        f"cache {cache_bytes(layer) / 2**20:.1f} MiB",
        flush=True,
    )
    for shadows, gather_samples in itertools.product(("embree", "shadowmaps"), args.gather_samples):
        relighter = open_gather_relighter(
            layer, shadows=shadows, settings=_relight_settings(args), gather_samples=gather_samples
        )
        sizes = {n: (s.num_representatives, s.num_gathers) for n, s in relighter.sets.items()}
        relighter.render()
        maps = getattr(relighter.direct.visibility, "seconds", None)
        before = dict(maps or {})
        timings = edit_timings(relighter, args.repeats, time.process_time if args.cpu_time else time.perf_counter)
        # Only the moves query the visibility (colour and shaping edits re-use their answers).
        split = (
            ""
            if maps is None
            else ", shadow maps per move: "
            + ", ".join(
                f"{kind} {1e3 * (maps[kind] - before.get(kind, 0.0)) / args.repeats:.0f} ms CPU"
                for kind in ("build", "lookup")
            )
        )
        print(
            f"  {shadows}, {gather_samples} gather samples: "
            + ", ".join(
                f"{kind} {full:.0f} ms (indirect {indirect:.0f} ms)" for kind, (full, indirect) in timings.items()
            )
            + f" (median of {args.repeats}, {'CPU' if args.cpu_time else 'wall'} time; sets (reps, entries) "
            f"{sizes}, {relighter.points.num_points} surface points, {relighter.cache_bytes / 2**20:.1f} MiB in memory)"
            + split,
            flush=True,
        )


def main(argv: list[str] | None = None) -> int:
    defaults = GatherSettings()
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", nargs="+", choices=sorted(SCENES))
    parser.add_argument("--width", type=int, default=32)
    parser.add_argument("--height", type=int, default=32)
    parser.add_argument("--clusters", type=int, nargs="+", default=[15, 30, 60, 120, 240])
    parser.add_argument("--representatives", type=int, nargs="+", default=[0], help="0: the default count")
    parser.add_argument("--point-cells", type=int, nargs="+", default=[defaults.point_cells])
    parser.add_argument("--directions", type=int, default=defaults.num_directions)
    parser.add_argument("--gather-samples", type=int, nargs="+", default=[DEFAULT_GATHER_SAMPLES])
    parser.add_argument("--spp", type=int, default=512, help="reference samples per pixel")
    parser.add_argument("--supersampling", type=int, default=1)
    parser.add_argument("--texture-samples", type=int, default=1)
    parser.add_argument("--shadows", default="embree", choices=("embree", "shadowmaps"))
    parser.add_argument(
        "--shadow-map-resolution",
        type=int,
        default=RelightSettings().shadow_map_resolution,
        help="texels per side of each shadow-map face (RelightSettings)",
    )
    parser.add_argument("--repeats", type=int, default=5, help="timed edits per median")
    parser.add_argument("--timing", action="store_true", help="edit timings of one cache per scene, no PSNR")
    parser.add_argument(
        "--cpu-time",
        action="store_true",
        help="--timing in this process's CPU time (run with OMP_NUM_THREADS=1 on a loaded machine)",
    )
    parser.add_argument("--reuse", action="store_true", help="--timing: relight OUT's cache if there is one")
    parser.add_argument("--out", help="directory for the scenes and caches (default: a temporary one)")
    parser.add_argument("--csv", help="also write the rows to this CSV file")
    args = parser.parse_args(argv)
    directory = Path(args.out or tempfile.mkdtemp(prefix="relight-gather-sweep-"))
    rows = []
    if not args.timing:
        print(",".join(COLUMNS), flush=True)
    for name in args.scenes:
        (directory / name).mkdir(parents=True, exist_ok=True)
        if args.timing:
            time_scene(name, args, directory / name)
        else:
            rows += sweep_scene(name, args, directory / name)
    if args.csv:
        write_csv(rows, args.csv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
