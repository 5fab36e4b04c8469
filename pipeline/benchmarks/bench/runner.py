"""`relight bench`'s run: every registered method's sweep on the bundled scenes, one CSV and JSON.

    run_bench(BenchConfig(out=..., quick=True)) -> BenchResult

Per scene it writes the stage and its example light edits under `out/scenes/<scene>`, renders each
reference once (`References`, cached under `out/references`, so a re-run into the same directory
re-uses them) and runs each method's grid (`methods.adapters`), caches under `out/caches`. Then
the path-tracer comparison rows (`comparison.py`), then `out/bench.csv`, `out/bench.json`,
`out/summary.txt` (each method's best speed-up) and the charts (`chart.py`). Everything but the
*_ms / bake_s timings is deterministic.
"""

from __future__ import annotations

import platform
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from pipeline.benchmarks.bench.comparison import SppCurve, comparison_rows, measure_spp_curve, summary
from pipeline.benchmarks.bench.measure import run_point
from pipeline.benchmarks.bench.methods import BenchScene, adapters
from pipeline.benchmarks.bench.references import References
from pipeline.benchmarks.rows import SweepRow, write_csv, write_json
from pipeline.scenes import SCENES, light_edit_layers
from relight_torch.io.atomic import write_text_atomic


@dataclass(frozen=True)
class BenchConfig:
    """What one bench run covers.

    Attributes:
        out: output directory (CSV, JSON, charts, references, caches).
        quick: the small grids (seconds per method) instead of the full sweeps.
        scenes: bundled scenes to run.
        methods: registered methods to run (None: all).
        edits: example light edits to relight under besides the shot (None: all of them).
        width, height: image size.
        spp: samples per pixel of the references the methods are compared with.
        curve_spp: spp of the low-spp path-tracer renders fitted for the comparison rows.
        repeats: timed light edits per relight_ms.
        device: torch device of the relighters.
    """

    out: Path
    quick: bool = False
    scenes: tuple[str, ...] = ("cornell_box", "glossy", "set")
    methods: tuple[str, ...] | None = None
    edits: tuple[str, ...] | None = None
    width: int = 160
    height: int = 120
    spp: int = 256
    curve_spp: tuple[int, ...] = (1, 2, 4, 8, 16)
    repeats: int = 7
    device: str = "cpu"

    @classmethod
    def quick_run(cls, out: Path, **overrides) -> BenchConfig:
        """The `--quick` configuration: the Cornell box at 24x24, small grids and references."""
        settings = dict(
            out=out, quick=True, scenes=("cornell_box",), width=24, height=24, spp=32, curve_spp=(1, 4), repeats=3
        )
        return cls(**{**settings, **overrides})


@dataclass
class BenchResult:
    """Rows of the run (methods then comparisons), the fitted path-tracer curves and the files written."""

    rows: list[SweepRow]
    curves: dict[tuple[str, int], SppCurve] = field(default_factory=dict)
    files: list[Path] = field(default_factory=list)


def prepare_scene(name: str, config: BenchConfig) -> BenchScene:
    """Write the bundled scene and its light edits; the BenchScene the adapters get."""
    bundled = SCENES[name]
    directory = config.out / "scenes" / name
    shot = bundled.write(directory)
    edits = light_edit_layers(name, directory)
    edits = {edit: layer for edit, layer in edits.items() if config.edits is None or edit in {"shot", *config.edits}}
    references = References(
        shot, bundled.camera, config.width, config.height, edits, config.spp, config.out / "references"
    )
    return BenchScene(
        name,
        shot,
        bundled.camera,
        config.width,
        config.height,
        edits,
        config.out / "caches" / name,
        config.device,
        config.repeats,
        references,
    )


def context(config: BenchConfig) -> dict[str, object]:
    """What the rows were measured on (the JSON's context). The output folder is left out: the JSON
    lies in it, and its absolute path would only name the machine the bench ran on."""
    settings = {key: value for key, value in asdict(config).items() if key != "out"}
    return {
        **{key: str(value) if isinstance(value, Path) else value for key, value in settings.items()},
        "torch_threads": torch.get_num_threads(),
        "machine": platform.machine(),
        "processor": platform.processor() or platform.machine(),
    }


def run_bench(config: BenchConfig, log=print) -> BenchResult:
    """Run the bench (see the module doc); `log` gets one line per finished grid point."""
    from pipeline.benchmarks.bench.chart import write_charts

    methods = adapters(config.methods)
    result = BenchResult([])
    for name in config.scenes:
        scene = prepare_scene(name, config)
        method_rows = []
        for adapter in methods.values():
            for point in adapter.grid(config.quick):
                rows = run_point(adapter, scene, point)
                method_rows += rows
                log(f"{name} {adapter.name} {point}: " + ", ".join(f"{r.light_edit} {r.psnr_db:.1f} dB" for r in rows))
        bounces = sorted({int(row.parameters()["bounces"]) for row in method_rows})
        for count in bounces:
            result.curves[(name, count)] = measure_spp_curve(scene.references, count, config.curve_spp)
        result.rows += method_rows + comparison_rows(method_rows, result.curves)
    csv_path, json_path = config.out / "bench.csv", config.out / "bench.json"
    write_csv(result.rows, csv_path)
    write_json(
        result.rows,
        json_path,
        {**context(config), "spp_curves": {f"{s}/b{b}": asdict(c) for (s, b), c in result.curves.items()}},
    )
    summary_path = config.out / "summary.txt"
    write_text_atomic(summary_path, summary(result.rows) + "\n")
    result.files = [csv_path, json_path, summary_path, *write_charts(result.rows, config.out)]
    return result
