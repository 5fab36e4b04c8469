"""The bench's charts, PNG files a person can read without the CSV.

speed_accuracy.png      per scene: PSNR under the shot's lights against relight ms on a log axis,
                        every point of every method, each method's Pareto front as a line, and
                        the path tracer rows (hollow: same time; cross: same PSNR, labelled with
                        the best speed-up; both are measured under the shot's lights)
params_<method>.png     per scene: PSNR and relight ms against the method's swept parameter
                        (`chart_axes[0]` of its adapter), one curve per combination of the other
                        parameters that vary (`chart_axes[1]` named first)
"""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

from matplotlib import ticker
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from pipeline.benchmarks.bench.methods import adapters
from pipeline.benchmarks.rows import SweepRow
from relight_torch.io.atomic import atomic_path

COMPARISONS = ("reference-equal-time", "reference-full")


def points(rows: list[SweepRow], edit: str | None = None) -> dict[tuple[str, str], list[tuple[str, float, float]]]:
    """(scene, method) -> [(params, mean PSNR over the edits, relight ms of the 'shot' edit)].

    Args:
        edit: average over this light edit only (None: over all of them).
    """
    psnrs: dict[tuple[str, str, str], list[float]] = defaultdict(list)
    times: dict[tuple[str, str, str], float] = {}
    for row in rows:
        key = (row.scene, row.method, row.params)
        if edit is None or row.light_edit == edit:
            psnrs[key].append(row.psnr_db)
        if row.light_edit == "shot":
            times[key] = row.relight_ms
    out: dict[tuple[str, str], list[tuple[str, float, float]]] = defaultdict(list)
    for (scene, method, params), values in psnrs.items():
        out[(scene, method)].append((params, sum(values) / len(values), times.get((scene, method, params), math.nan)))
    return out


def pareto_front(curve: list[tuple[str, float, float]]) -> list[tuple[str, float, float]]:
    """The points no other point beats in both PSNR (higher) and time (lower), by increasing time."""
    front = []
    for point in sorted((p for p in curve if math.isfinite(p[2]) and math.isfinite(p[1])), key=lambda p: (p[2], -p[1])):
        if not front or point[1] > front[-1][1]:
            front.append(point)
    return front


def _log_axis(axes, which: str) -> None:
    """Axis `which` ('x' or 'y') of `axes` on a log scale, labelled 12, 50, 300 (not 10^n)."""
    axis = axes.xaxis if which == "x" else axes.yaxis
    (axes.set_xscale if which == "x" else axes.set_yscale)("log")
    axis.set_major_locator(ticker.LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(ticker.FuncFormatter(lambda value, _: f"{value:.0f}" if value >= 1 else f"{value:g}"))
    axis.set_minor_formatter(ticker.NullFormatter())


def _save(figure: Figure, path: Path) -> Path:
    with atomic_path(path) as temp:
        figure.savefig(temp, format="png", dpi=110, bbox_inches="tight")
    return path


def speed_accuracy_chart(rows: list[SweepRow], path: Path) -> Path:
    """Write speed_accuracy.png (see the module doc)."""
    by_method = points(rows, "shot")
    scenes = list(dict.fromkeys(row.scene for row in rows))
    methods = list(dict.fromkeys(row.method for row in rows if row.method not in COMPARISONS))
    figure = Figure(figsize=(8.4 * len(scenes), 4.8))
    for index, scene in enumerate(scenes):
        axes = figure.add_subplot(1, len(scenes), index + 1)
        first = next(row for row in rows if row.scene == scene)
        for colour_index, method in enumerate(methods):
            colour = f"C{colour_index}"
            curve = [p for p in by_method.get((scene, method), []) if math.isfinite(p[2])]
            if not curve:
                continue
            axes.scatter([p[2] for p in curve], [p[1] for p in curve], color=colour, alpha=0.35, s=18)
            front = pareto_front(curve)
            axes.plot([p[2] for p in front], [p[1] for p in front], "-o", color=colour, label=method)
            compared = [r for r in rows if r.scene == scene and r.parameters().get("vs") == method]
            same_time = [r for r in compared if r.method == "reference-equal-time"]
            same_psnr = [r for r in compared if r.method == "reference-full"]
            axes.scatter(
                [r.relight_ms for r in same_time],
                [r.psnr_db for r in same_time],
                facecolors="none",
                edgecolors=colour,
                s=36,
            )
            axes.scatter(
                [r.relight_ms for r in same_psnr], [r.psnr_db for r in same_psnr], marker="x", color=colour, s=36
            )
            if same_psnr:
                best = max(same_psnr, key=lambda r: float(r.parameters()["speedup"]))
                bound = ">= " if best.parameters()["bound"] == "lower" else ""
                speedup = float(best.parameters()["speedup"])
                axes.annotate(
                    f"{bound}{speedup:.0f}x" if speedup >= 10 else f"{bound}{speedup:.1f}x",
                    (best.relight_ms, best.psnr_db),
                    textcoords="offset points",
                    xytext=(4, 4),
                    fontsize=8,
                    color=colour,
                )
        _log_axis(axes, "x")
        axes.set_xlabel(f"relight time per light move, ms (log; {first.device})")
        axes.set_ylabel("PSNR against the path tracer, dB (shot's lights)")
        axes.set_title(f"{scene} {first.width}x{first.height}: line = Pareto front, faint = other points")
        axes.grid(True, which="both", alpha=0.3)
        handles, labels = axes.get_legend_handles_labels()
        handles += [
            Line2D([], [], ls="", marker="o", mfc="none", color="grey"),
            Line2D([], [], ls="", marker="x", color="grey"),
        ]
        labels += ["path tracer in the method's time", "path tracer to the method's PSNR (speed-up)"]
        axes.legend(handles, labels, fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return _save(figure, path)


def parameter_chart(rows: list[SweepRow], method: str, x_key: str, series_key: str | None, path: Path) -> Path:
    """Write one method's parameter chart (see the module doc)."""
    by_method = points(rows)
    scenes = [scene for scene in dict.fromkeys(row.scene for row in rows) if (scene, method) in by_method]
    figure = Figure(figsize=(5.6 * len(scenes), 7.2))
    for index, scene in enumerate(scenes):
        measured = [
            (dict(item.split("=", 1) for item in params.split()), mean_psnr, ms)
            for params, mean_psnr, ms in by_method[(scene, method)]
        ]
        # One curve per combination of the other parameters that vary (series_key first).
        varying = [key for key in measured[0][0] if key != x_key and len({v.get(key) for v, _, _ in measured}) > 1]
        varying.sort(key=lambda key: key != series_key)
        series: dict[str, list[tuple[float, float, float]]] = defaultdict(list)
        for values, mean_psnr, ms in measured:
            label = " ".join(f"{key}={values.get(key)}" for key in varying) or method
            series[label].append((float(values[x_key]), mean_psnr, ms))
        top = figure.add_subplot(2, len(scenes), index + 1)
        bottom = figure.add_subplot(2, len(scenes), len(scenes) + index + 1, sharex=top)
        for label, values in series.items():
            values.sort()
            top.plot([v[0] for v in values], [v[1] for v in values], "-o", label=label)
            bottom.plot([v[0] for v in values], [v[2] for v in values], "-o", label=label)
        first = next(row for row in rows if row.scene == scene)
        top.set_title(f"{method} on {scene} {first.width}x{first.height}")
        top.set_ylabel("PSNR, dB (mean over light edits)")
        bottom.set_ylabel(f"relight ms per light move ({first.device})")
        _log_axis(bottom, "y")
        bottom.set_xlabel(x_key)
        for axes in (top, bottom):
            axes.grid(True, alpha=0.3)
            axes.legend(fontsize=7)
    return _save(figure, path)


def write_charts(rows: list[SweepRow], out: Path) -> list[Path]:
    """speed_accuracy.png and one params_<method>.png per method with rows; the paths written."""
    written = [speed_accuracy_chart(rows, out / "speed_accuracy.png")]
    present = {row.method for row in rows}
    for name, adapter in adapters().items():
        if name in present:
            written.append(parameter_chart(rows, name, *adapter.chart_axes, out / f"params_{name}.png"))
    return written
