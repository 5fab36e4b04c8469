"""`relight bench --progressive`: PSNR against elapsed time after each light edit, for the relighter's
progressive frames and for re-rendering with a path tracer from the same start.

    python -m pipeline.benchmarks.bench.time_to_quality --out docs/bench/progressive [--width 640 --height 480] \
        [--reference-size 80 60 --spp 512] [--path-spp 64] [--mitsuba-spp 32] [--shot-cache L --direct-cache L]

On the Cornell box (`pipeline.benchmarks.progressive.prepare`: the shot cache and the direct cache at
--width x --height, the edits colour, shaping, move and new light). Per cache and edit: the rig before
the edit is rendered (the relighter warm, as in a session), the edit is made and `progressive_frames`
runs to the exact frame; each frame gives a point (wall ms since the edit, PSNR). A first edit per
kind is not counted (it builds the coarse levels' upsampling weights and teaches the cost model).

The path tracers start from the same rig after the edit and accumulate passes of 1, 1, 2, 4, ... spp
(cumulative 1, 2, 4, ..., --path-spp), each pass seeded anew; a point per pass (the summed render
seconds of the passes so far, PSNR of their mean). Their scene set-up (BVH build, Mitsuba's scene
load) is not counted, which favours them. The project's `PathTracer` and, where the `mitsuba` package
is installed, Mitsuba 3 (`pipeline.reference.mitsuba_scene`, the bridge the agreement check uses;
an edit it cannot convert, such as shaping, is noted and skipped).

Every image is compared with the same full-GI reference: the project's path tracer at
--reference-size and --spp, seeded apart from every pass so that its noise is independent of
theirs; the relit frames are box-filtered to it and the path tracers rendered at that size.
Rendering the path tracers at the reference size costs the same per path as rendering --width x
--height and box-filtering (each reference pixel averages as many paths either way), and keeps the
comparison within reach of a CPU.

The speed-up at L dB (30, 35, 40) is the time the path tracer needs to reach L over the time the
relighter needs: the relighter's time is the first frame at or above L; the path tracer's is
interpolated between its passes (MSE linear in 1/spp, time linear in spp), or, past its last pass,
extrapolated by MSE ~ 1/spp from it (marked 'extrapolated'). A level never reached by the relighter
(its converged frame below it) has no speed-up.

Writes OUT/time_to_quality.csv (one row per point), OUT/time_to_quality_speedups.csv,
OUT/time_to_quality.md and OUT/time_to_quality.png.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pipeline.bake.shot import DEFAULT_TARGET_DB
from pipeline.benchmarks import run_in_work
from pipeline.benchmarks.bench.measure import machine_description
from pipeline.benchmarks.progressive import Setup, csv_cell, downsampled, prepare, references_of
from pipeline.errors import RelightError
from pipeline.reference.path_tracer import FULL_FRAME_BOUNCES, PathTracer, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from relight_torch import open_cache
from relight_torch.io.atomic import atomic_path, write_text_atomic
from relight_torch.metrics import psnr
from relight_torch.progressive import CostModel, level_label, progressive_frames

EDITS = ("colour", "shaping", "move", "new light")
LEVELS_DB = (30.0, 35.0, 40.0)
FIELDS = ("renderer", "edit", "step", "elapsed_ms", "cpu_ms", "psnr_db", "detail")
CLOCKS = ("cpu_ms", "elapsed_ms")
"""The two times of a point: the process's CPU ms (all threads: the work, little disturbed by a
shared machine) and wall ms."""


@dataclasses.dataclass(frozen=True)
class Point:
    """One point of a curve.

    Attributes:
        renderer: 'relighter <cache>' or a path tracer's name.
        edit: the edit kind.
        step: the frame's level ('1/16' ... 'exact') or the spp so far.
        elapsed_ms: wall ms from the edit to this image.
        cpu_ms: the process's CPU ms (all threads) from the edit to this image.
        psnr_db: against the reference.
        detail: the pass's spp.
    """

    renderer: str
    edit: str
    step: str
    elapsed_ms: float
    cpu_ms: float
    psnr_db: float
    detail: str = ""


def relighter_curve(layer: Path, label: str, setup: Setup, edits, reference: dict, args) -> list[Point]:
    """The relighter's progressive frames after each edit (the second edit of each kind; see the module doc)."""
    relighter = open_cache(layer)
    costs = CostModel()
    size = tuple(args.reference_size)
    points: list[Point] = []
    for edit in edits:
        for k in (1, 0):  # k = 1 warms up; k = 0 is the rig the reference shows
            before, after = setup.rigs[edit](k)
            relighter.set_lights(before)
            relighter.render()
            relighter.set_lights(after)
            cpu = time.process_time()
            frames = []  # compared after the last one: the frames' clock runs while the caller works
            for frame in progressive_frames(relighter, args.budget_ms, costs=costs):
                frames.append((frame, 1e3 * (time.process_time() - cpu)))
        for frame, cpu_ms in frames:
            step = level_label(frame.stride)
            image = downsampled(frame.image, size)
            points.append(Point(label, edit, step, frame.elapsed_ms, cpu_ms, psnr(image, reference[edit])))
        print(
            f"{label} {edit}: "
            + ", ".join(f"{p.step} {p.elapsed_ms:.0f} ms {p.psnr_db:.1f} dB" for p in points[-len(frames) :]),
            flush=True,
        )
    return points


def pass_spp(total: int) -> list[int]:
    """The spp of the passes: 1, 1, 2, 4, ... summing to the largest power of two <= `total`."""
    passes, done = [1], 1
    while done * 2 <= total:
        passes.append(done)
        done *= 2
    return passes


def path_curve(
    name: str, render: Callable[[int, int], np.ndarray], edit: str, reference: np.ndarray, total: int
) -> list[Point]:
    """A path tracer's progressive curve: `render(spp, seed)` -> (H, W, 3) mean per pass, timed here."""
    points, elapsed, cpu, done = [], 0.0, 0.0, 0
    accumulated = np.zeros_like(reference, dtype=np.float64)
    for seed, spp in enumerate(pass_spp(total), start=1):
        start, start_cpu = time.perf_counter(), time.process_time()
        image = render(spp, seed)
        elapsed += time.perf_counter() - start
        cpu += time.process_time() - start_cpu
        accumulated += image.astype(np.float64) * spp
        done += spp
        mean = (accumulated / done).astype(np.float32)
        points.append(Point(name, edit, str(done), 1e3 * elapsed, 1e3 * cpu, psnr(mean, reference), f"{spp} spp pass"))
    print(
        f"{name} {edit}: " + ", ".join(f"{p.step} spp {p.elapsed_ms:.0f} ms {p.psnr_db:.1f} dB" for p in points),
        flush=True,
    )
    return points


def path_tracer_curves(setup: Setup, edits, references: dict, args) -> tuple[list[Point], list[str]]:
    """The project's path tracer's and (where installed and the edit converts) Mitsuba 3's curves."""
    size = tuple(args.reference_size)
    scene = load_scene(setup.shot, width=size[0], height=size[1])
    camera = find_camera(scene, setup.camera_path)
    points, notes = [], []
    try:
        from pipeline.reference import mitsuba_scene
    except ImportError:
        mitsuba_scene = None
        notes.append("Mitsuba 3 is not installed: no Mitsuba curves.")
    for edit in edits:
        lit = dataclasses.replace(scene, lights=setup.rigs[edit](0)[1])

        def ours(spp: int, seed: int, lit=lit) -> np.ndarray:
            return PathTracer(lit, ReferenceSettings(spp=spp, seed=1000 + seed)).render(camera).mean

        points += path_curve("path tracer (ours)", ours, edit, references[edit], args.path_spp)
        if mitsuba_scene is None or args.mitsuba_spp < 1:
            continue
        try:
            loaded = mitsuba_renderer(mitsuba_scene, lit, camera)
        except ValueError as error:
            notes.append(f"Mitsuba 3, {edit}: not converted ({error}).")
            continue
        points += path_curve("Mitsuba 3", loaded, edit, references[edit], args.mitsuba_spp)
    return points, notes


def mitsuba_renderer(bridge, scene, camera) -> Callable[[int, int], np.ndarray]:
    """`render(spp, seed)` -> (H, W, 3) of Mitsuba 3 on the scene loaded once by the bridge
    (`pipeline.reference.mitsuba_scene`), the full frame's bounce cap.

    Raises:
        ValueError: the scene does not convert (the bridge names what).
    """
    import mitsuba as mi

    mi.set_variant(bridge.VARIANT)
    loaded = mi.load_dict(bridge.scene_dict(scene, camera, FULL_FRAME_BOUNCES, 1))

    def render(spp: int, seed: int) -> np.ndarray:
        return np.array(mi.render(loaded, spp=spp, seed=seed), dtype=np.float32)

    return render


def time_to(points: list[Point], level: float, clock: str) -> float | None:
    """`clock` ms (a `CLOCKS` name) of the first point at or above `level` dB (a relighter's
    frames), None if none is."""
    return next((getattr(p, clock) for p in points if p.psnr_db >= level), None)


def path_time_to(points: list[Point], level: float, clock: str) -> tuple[float, bool] | None:
    """(ms, extrapolated) for a path tracer to reach `level` dB: between its passes MSE is taken
    linear in 1/spp and time linear in spp; past the last one, MSE ~ 1/spp from it."""
    target = 10.0 ** (-level / 10.0)
    previous = None
    for point in points:
        spp, mse = int(point.step), psnr_to_mse(point.psnr_db)
        if mse <= target:
            if previous is None:
                return getattr(point, clock), False
            spp0, mse0, ms0 = previous
            # mse = alpha + beta / spp through both points; solve for the spp giving `target`.
            beta = (mse0 - mse) / (1.0 / spp0 - 1.0 / spp)
            alpha = mse - beta / spp
            needed = beta / (target - alpha) if target > alpha and beta > 0 else spp
            needed = min(max(needed, spp0), spp)
            return ms0 + (getattr(point, clock) - ms0) * (needed - spp0) / (spp - spp0), False
        previous = (spp, mse, getattr(point, clock))
    if previous is None:
        return None
    spp, mse, ms = previous
    return ms * (mse / target), True


def psnr_to_mse(db: float) -> float:
    return 0.0 if math.isinf(db) else 10.0 ** (-db / 10.0)


def speedups(points: list[Point], edits, relighters: list[str], tracers: list[str], clock: str) -> list[dict]:
    """Rows (edit, relighter, path tracer, level, relighter ms, path tracer ms, speed-up, note) on `clock`."""
    rows = []
    for edit in edits:
        for relighter in relighters:
            frames = [p for p in points if p.renderer == relighter and p.edit == edit]
            for tracer in tracers:
                passes = [p for p in points if p.renderer == tracer and p.edit == edit]
                if not frames or not passes:
                    continue
                for level in LEVELS_DB:
                    mine, theirs = time_to(frames, level, clock), path_time_to(passes, level, clock)
                    row = {"edit": edit, "relighter": relighter, "path_tracer": tracer, "level_db": level}
                    row["relighter_ms"] = mine
                    row["path_tracer_ms"] = None if theirs is None else theirs[0]
                    row["speedup"] = None if mine is None or theirs is None else theirs[0] / mine
                    row["note"] = (
                        "relighter never reaches it (its converged frame is below)"
                        if mine is None
                        else (
                            "path tracer extrapolated (MSE ~ 1/spp past its last pass)" if theirs and theirs[1] else ""
                        )
                    )
                    rows.append(row)
    return rows


def write_chart(points: list[Point], edits, path: Path) -> None:
    """One figure, a panel per edit: PSNR against CPU ms after the edit (log), a curve per renderer."""
    from matplotlib.figure import Figure

    columns = min(2, len(edits))
    rows = -(-len(edits) // columns)
    figure = Figure(figsize=(6.0 * columns, 4.2 * rows))
    renderers = list(dict.fromkeys(p.renderer for p in points))
    for index, edit in enumerate(edits):
        axes = figure.add_subplot(rows, columns, index + 1)
        for renderer in renderers:
            curve = [p for p in points if p.renderer == renderer and p.edit == edit]
            if curve:
                style = "-o" if renderer.startswith("relighter") else "--s"
                axes.plot([p.cpu_ms for p in curve], [p.psnr_db for p in curve], style, label=renderer, markersize=4)
        for level in LEVELS_DB:
            axes.axhline(level, color="0.85", linewidth=0.8, zorder=0)
        axes.set_xscale("log")
        axes.set_title(f"after a {edit} edit")
        axes.set_xlabel("CPU ms after the edit (all threads)")
        axes.set_ylabel("PSNR (dB) against the full-GI reference")
        axes.grid(True, which="major", alpha=0.3)
        axes.legend(fontsize=7)
    figure.tight_layout()
    with atomic_path(path) as temporary:
        figure.savefig(temporary, format="png", dpi=110)


DEFAULTS = {"width": 640, "height": 480, "spp": 512, "edits": list(EDITS)}
"""The defaults of the options `relight bench` shares (its own defaults are its sweep's)."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--width", type=int, default=DEFAULTS["width"])
    parser.add_argument("--height", type=int, default=DEFAULTS["height"])
    parser.add_argument("--spp", type=int, default=DEFAULTS["spp"], help="the reference's samples per pixel")
    parser.add_argument("--edits", nargs="+", choices=EDITS, default=DEFAULTS["edits"], metavar="EDIT")
    add_progressive_options(parser)
    return run(parser.parse_args(argv))


def add_progressive_options(parser: argparse.ArgumentParser) -> None:
    """The options of the time-to-quality run that `relight bench` lacks (see `with_defaults`)."""
    parser.add_argument(
        "--reference-size",
        type=int,
        nargs=2,
        default=(80, 60),
        metavar=("W", "H"),
        help="--progressive: the full-GI reference's size, dividing --width x --height (default 80 60)",
    )
    parser.add_argument(
        "--path-spp", type=int, default=64, help="--progressive: the project's path tracer's last cumulative spp"
    )
    parser.add_argument(
        "--mitsuba-spp", type=int, default=32, help="--progressive: Mitsuba 3's last cumulative spp (0: none)"
    )
    parser.add_argument("--budget-ms", type=float, default=33.0, help="--progressive: the first frame's budget")
    parser.add_argument("--shot-size", type=int, nargs=2, default=(160, 120), help=argparse.SUPPRESS)
    parser.add_argument("--quality", type=float, default=DEFAULT_TARGET_DB, help=argparse.SUPPRESS)
    parser.add_argument(
        "--shot-cache", type=Path, help="--progressive: a shot cache of the Cornell box at --width x --height"
    )
    parser.add_argument("--direct-cache", type=Path, help="--progressive: a direct cache of it")
    parser.add_argument("--work", type=Path, help="--progressive: bakes and references kept between runs")


def with_defaults(args: argparse.Namespace) -> argparse.Namespace:
    """`relight bench --progressive`'s arguments with this run's defaults where it left the shared
    options unset (None), the edits checked.

    Raises:
        RelightError: an edit this run does not know.
    """
    values = vars(args).copy()
    for name, default in DEFAULTS.items():
        if values.get(name) is None:
            values[name] = default
    unknown = [edit for edit in values["edits"] if edit not in EDITS]
    if unknown:
        raise RelightError(f"--edits {' '.join(unknown)}: --progressive knows {', '.join(EDITS)}")
    values["out"] = Path(values["out"])
    return argparse.Namespace(**values)


def run(args: argparse.Namespace) -> int:
    """The run (see the module doc); the files go into args.out."""
    for name in ("width", "height", "spp", "path_spp"):
        if getattr(args, name) < 1:
            raise RelightError(f"--{name.replace('_', '-')} must be at least 1, got {getattr(args, name)}")
    if args.width % args.reference_size[0] or args.height % args.reference_size[1]:
        raise RelightError(f"--reference-size {args.reference_size} must divide {args.width}x{args.height}")
    args.out.mkdir(parents=True, exist_ok=True)
    return run_in_work(args.work, lambda work: _run(args, work))


def _run(args: argparse.Namespace, work: Path) -> int:
    load = os.getloadavg()
    setup = prepare(args, work)
    references = references_of(setup, args.edits, tuple(args.reference_size), args.spp, work)
    relighters = [f"relighter, {setup.shot_label}", "relighter, direct"]
    points = relighter_curve(setup.shot_layer, relighters[0], setup, args.edits, references, args)
    points += relighter_curve(setup.direct_layer, relighters[1], setup, args.edits, references, args)
    tracer_points, notes = path_tracer_curves(setup, args.edits, references, args)
    points += tracer_points
    tracers = list(dict.fromkeys(p.renderer for p in tracer_points))
    rows = {clock: speedups(points, args.edits, relighters, tracers, clock) for clock in CLOCKS}
    _write(args, setup, points, rows, notes, load + os.getloadavg())
    return 0


def _write(args, setup: Setup, points: list[Point], rows: dict[str, list[dict]], notes: list[str], load) -> None:
    out = args.out
    relighter_names = [name for name in dict.fromkeys(p.renderer for p in points) if name.startswith("relighter")]
    lines = [",".join(FIELDS)] + [",".join(csv_cell(getattr(point, name)) for name in FIELDS) for point in points]
    write_text_atomic(out / "time_to_quality.csv", "\n".join(lines) + "\n")
    names = ("edit", "relighter", "path_tracer", "level_db", "relighter_ms", "path_tracer_ms", "speedup", "note")
    lines = ["clock," + ",".join(names)] + [
        ",".join([clock] + [csv_cell(row[name]) for name in names]) for clock in CLOCKS for row in rows[clock]
    ]
    write_text_atomic(out / "time_to_quality_speedups.csv", "\n".join(lines) + "\n")
    write_chart(points, args.edits, out / "time_to_quality.png")
    command = (
        f"relight bench --progressive --out {out} --width {args.width} --height {args.height} --reference-size "
        f"{args.reference_size[0]} {args.reference_size[1]} --spp {args.spp} --path-spp {args.path_spp} "
        f"--mitsuba-spp {args.mitsuba_spp} --budget-ms {args.budget_ms:g} --edits "
        + " ".join(f"'{edit}'" for edit in args.edits)
        + (f" --shot-cache {args.shot_cache}" if args.shot_cache else "")
        + (f" --direct-cache {args.direct_cache}" if args.direct_cache else "")
    )
    text = [
        "# Time to quality after a light edit: the relighter's progressive frames against re-rendering",
        "",
        f"Generated by `{command}`.",
        "",
        f"Cornell box, relit at {args.width}x{args.height} (the shot cache: {setup.sizes}; the direct cache, "
        f"supersampling 2), budget {args.budget_ms:g} ms. Every image against the same full-GI reference: the "
        f"project's path tracer at {args.reference_size[0]}x{args.reference_size[1]}, {args.spp} spp; relit "
        "frames box-filtered to it, path tracers rendered at it (their set-up not counted). Chart: "
        "[time_to_quality.png](time_to_quality.png) (CPU ms); every point: time_to_quality.csv. Path-tracer "
        "spp are cumulative; relighter steps are the progressive levels (1/p: one shaded point per p x p pixels).",
        "",
    ]
    move = [p for p in points if p.renderer == relighter_names[0] and p.edit == "move"]
    if move:
        reached = next((p for p in move if p.psnr_db >= 35.0), None)
        text += [
            "Time to 35 dB after a light move, "
            + relighter_names[0]
            + (
                f": {reached.cpu_ms:.0f} CPU ms, {reached.elapsed_ms:.0f} wall ms (level {reached.step}, "
                f"{reached.psnr_db:.1f} dB)."
                if reached
                else f": not reached (converged frame {move[-1].psnr_db:.1f} dB)."
            ),
            "",
        ]
    titles = {"cpu_ms": "CPU ms (all threads: the work)", "elapsed_ms": "wall ms (disturbed by the machine's load)"}
    for clock in CLOCKS:
        text += [
            f"## Speed-up at equal PSNR, {titles[clock]}: path tracer's time / relighter's time",
            "",
            "| edit | relighter | path tracer | dB | relighter ms | path tracer ms | speed-up | note |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for row in rows[clock]:
            if row["relighter_ms"] is None:
                continue  # listed below the tables
            speedup = "-" if row["speedup"] is None else f"{row['speedup']:.0f}x"
            text.append(
                f"| {row['edit']} | {row['relighter']} | {row['path_tracer']} | {row['level_db']:g} | "
                f"{_ms(row['relighter_ms'])} | {_ms(row['path_tracer_ms'])} | {speedup} | {row['note']} |"
            )
        text.append("")
    never = sorted(
        {(row["edit"], row["relighter"], row["level_db"]) for row in rows[CLOCKS[0]] if row["relighter_ms"] is None}
    )
    if never:
        text += [
            "Levels a relighter never reaches (its converged frame is below them against the full-GI reference): "
            + "; ".join(f"{relighter}, {edit}: {level:g} dB" for edit, relighter, level in never)
            + ".",
            "",
        ]
    text += ["## Curves (step: CPU ms / wall ms after the edit, PSNR dB)", ""]
    for edit in args.edits:
        text += [f"**{edit}**", ""]
        for renderer in dict.fromkeys(p.renderer for p in points):
            curve = [p for p in points if p.renderer == renderer and p.edit == edit]
            if curve:
                steps = ", ".join(f"{p.step}: {p.cpu_ms:.0f} / {p.elapsed_ms:.0f} ms, {p.psnr_db:.1f}" for p in curve)
                text.append(f"- {renderer}: {steps}")
        text.append("")
    text += [f"- {note}" for note in notes]
    text += [
        "",
        f"Machine: {machine_description()}; load average {load[0]:.1f} / {load[3]:.1f} (1 min, start / end). "
        "The machine was shared with other work: wall times are inflated by that load (CPU ms much less); "
        "re-run the command on a quiet machine for clean wall figures.",
        "",
    ]
    write_text_atomic(out / "time_to_quality.md", "\n".join(text))


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f}"


if __name__ == "__main__":
    raise SystemExit(main())
