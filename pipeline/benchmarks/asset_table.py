"""The real-asset table: every suite asset x method x resolution, through the commands a user runs.

Each cell writes the asset's shot (`suite_assets.SUITE`), bakes it with `relight bake` (one
method of the registry with the small settings of `tiny_caches.METHOD_OPTIONS`, or the default
shot cache, whose pilot bakes size it), relights it with `relight render` under the shot's own
lights and compares the frame with `relight reference` of the full frame (every bounce) at the
same size. It records whether the bake and the render succeeded (else the command's one-line
error: no cell may be a traceback), the PSNR, the bake and render seconds and the cache bytes.

    python -m pipeline.benchmarks.asset_table [--sizes 32x24 64x48] [--spp 64] [--work DIR]

writes docs/bench/ASSET_TABLE.md.
Timings are wall-clock seconds on whatever else the machine is running; re-measure on a quiet one.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.bake.adapter import cache_bytes
from pipeline.benchmarks import run_in_work
from pipeline.benchmarks.suite_assets import SUITE, SuiteAsset
from pipeline.benchmarks.tiny_caches import METHOD_OPTIONS, quiet_main
from relight_torch.io.atomic import atomic_path
from relight_torch.io.exr import read_exr
from relight_torch.metrics import psnr

SHOT_CACHE = "shot"
"""The row of the default shot cache (`relight bake` without --method)."""
METHODS = (*METHOD_OPTIONS, SHOT_CACHE)
SIZES = ((32, 24), (64, 48))
"""The full table's resolutions (width, height)."""
REFERENCE_SPP = 64
"""Path-tracer samples per pixel of the references."""


@dataclass(frozen=True)
class Cell:
    """One asset x method x resolution.

    Attributes:
        asset, method: the row; size: (width, height).
        baked, rendered: whether `relight bake` / `relight render` exited 0.
        error: the failing command's one-line message ('' when both succeeded).
        psnr: dB against the reference (nan when not rendered).
        bake_seconds, render_seconds: wall-clock seconds of the commands (nan when not run).
        cache_bytes: bytes of the cache's payloads (0 when not baked).
    """

    asset: str
    method: str
    size: tuple[int, int]
    baked: bool
    rendered: bool
    error: str
    psnr: float
    bake_seconds: float
    render_seconds: float
    cache_bytes: int


def _error_line(stderr: str) -> str:
    """The command's one-line error (the last 'relight: error' line), else its last line."""
    lines = [line for line in stderr.splitlines() if line.strip()]
    errors = [line for line in lines if "error:" in line]
    return (errors or lines or ["(no message)"])[-1].strip()


def _rgb(path: Path) -> np.ndarray:
    channels, _ = read_exr(path)
    return np.stack([channels["R"], channels["G"], channels["B"]], axis=-1)


def _timed(arguments: list[str]) -> tuple[int, str, float]:
    start = time.perf_counter()
    status, stderr = quiet_main(arguments)
    return status, stderr, time.perf_counter() - start


def reference(shot: Path, camera: str, size: tuple[int, int], out: Path, spp: int) -> Path:
    """The full-frame reference of a shot at `size`, rendered once into `out` (kept between runs).

    Raises:
        RuntimeError: the reference command failed (the table cannot be measured without it).
    """
    if not out.exists():
        status, stderr, _ = _timed(
            ["reference", str(shot), "--camera", camera, "--width", str(size[0]), "--height", str(size[1])]
            + ["--spp", str(spp), "-o", str(out)]
        )
        if status != 0:
            raise RuntimeError(f"reference of {shot} at {size[0]}x{size[1]}: {_error_line(stderr)}")
    return out


def measure_cell(asset: SuiteAsset, method: str, size: tuple[int, int], work: Path, spp: int = REFERENCE_SPP) -> Cell:
    """Bake, render and compare one cell in `work`/<asset> (the shot and its references are shared
    by the asset's cells)."""
    folder = work / asset.name
    shot = asset.write(folder / "shot")
    name = f"{method}_{size[0]}x{size[1]}"
    truth = reference(shot, asset.camera, size, folder / f"reference_{size[0]}x{size[1]}.exr", spp)
    bake = ["bake", str(shot), "--camera", asset.camera, "--out", str(folder / name), "--stem", "cache"]
    bake += ["--width", str(size[0]), "--height", str(size[1])]
    if method != SHOT_CACHE:
        bake += ["--method", method, *METHOD_OPTIONS[method]]
    bake += list(asset.bake_options.get(method, ()))
    nan = float("nan")
    status, stderr, bake_seconds = _timed(bake)
    if status != 0:
        return Cell(asset.name, method, size, False, False, _error_line(stderr), nan, bake_seconds, nan, 0)
    layer = folder / name / "cache.relight.usda"
    frame = folder / f"{name}.exr"
    status, stderr, render_seconds = _timed(["render", str(layer), "-o", str(frame)])
    size_bytes = cache_bytes(layer)
    if status != 0:
        return Cell(asset.name, method, size, True, False, _error_line(stderr), nan, bake_seconds, nan, size_bytes)
    quality = psnr(_rgb(frame), _rgb(truth))
    return Cell(asset.name, method, size, True, True, "", quality, bake_seconds, render_seconds, size_bytes)


def measure_table(
    work: Path,
    assets: Sequence[SuiteAsset] = SUITE,
    methods: Sequence[str] = METHODS,
    sizes: Sequence[tuple[int, int]] = SIZES,
    spp: int = REFERENCE_SPP,
    log: Callable[[str], None] = print,
) -> list[Cell]:
    """Every cell of assets x methods x sizes, measured in `work`."""
    cells = []
    for asset in assets:
        for size in sizes:
            for method in methods:
                cell = measure_cell(asset, method, size, work, spp)
                log(_row(cell))
                cells.append(cell)
    return cells


def _row(cell: Cell) -> str:
    def number(value: float, digits: int) -> str:
        return "-" if np.isnan(value) else f"{value:.{digits}f}"

    status = "yes" if cell.rendered else ("baked" if cell.baked else "no")
    return (
        f"| {cell.asset} | {cell.method} | {cell.size[0]}x{cell.size[1]} | {status} | {number(cell.psnr, 1)} | "
        f"{number(cell.bake_seconds, 1)} | {number(cell.render_seconds, 1)} | {cell.cache_bytes:,} | "
        f"{cell.error.replace('|', '/')} |"
    )


def table_markdown(cells: Sequence[Cell], command: str, spp: int) -> str:
    """The table as a Markdown document."""
    lines = [
        "# Real-asset table",
        "",
        "Every suite asset (`pipeline/benchmarks/suite_assets.py`, provenance in tests/data/scene/PROVENANCE.md)",
        "x relighting method (small settings; `shot` is the default shot cache) x resolution, baked with",
        "`relight bake`, relit with `relight render` under the shot's lights, and compared with `relight reference`'s",
        f"full frame (every bounce, {spp} samples per pixel) at the same size. Seconds are wall-clock on a shared",
        "machine (other work running); the PSNR includes the reference's own noise.",
        "",
        f"Written by `{command}`.",
        "",
        "| asset | method | size | baked and rendered | PSNR dB | bake s | render s | cache bytes | error |",
        "|---|---|---|---|---|---|---|---|---|",
        *(_row(cell) for cell in cells),
        "",
    ]
    return "\n".join(lines)


def size_argument(text: str) -> tuple[int, int]:
    width, _, height = text.partition("x")
    return int(width), int(height)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("docs/bench/ASSET_TABLE.md"))
    parser.add_argument("--work", type=Path, default=None, help="keep shots, caches and references here")
    parser.add_argument("--sizes", type=size_argument, nargs="+", default=list(SIZES), metavar="WxH")
    parser.add_argument("--spp", type=int, default=REFERENCE_SPP)
    parser.add_argument("--assets", nargs="+", default=[a.name for a in SUITE], choices=[a.name for a in SUITE])
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    args = parser.parse_args(argv)
    assets = [a for a in SUITE if a.name in args.assets]
    given = sys.argv[1:] if argv is None else argv
    # The work folder changes nothing measured (and is a machine path): not recorded.
    shown = [a for i, a in enumerate(given) if a != "--work" and (i == 0 or given[i - 1] != "--work")]
    command = " ".join(["python -m pipeline.benchmarks.asset_table", *shown])

    def run(work: Path) -> int:
        cells = measure_table(work, assets, args.methods, args.sizes, args.spp)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(args.out) as temporary:
            temporary.write_text(table_markdown(cells, command, args.spp))
        print(args.out)
        return 0

    return run_in_work(args.work, run)


if __name__ == "__main__":
    raise SystemExit(main())
