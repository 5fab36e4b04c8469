"""The exterior production shot at film sizes: what its bake and a lighting session cost.

    python -m pipeline.benchmarks.exterior [--teapots 1000] [--sizes 640x480 1920x1080]
        [--kinds direct shot] [--repeats 7] [--work DIR] [--out docs/bench/exterior]

The shot is `suite_assets.write_exterior_shot` (instanced and point-instanced Utah teapots on a
floor, a distant light and sixteen sphere lights, open sky in the top half of the frame). Per size
and cache kind (`direct`: `--method direct`; `shot`: the default bake, which chooses its
components by measurement), `relight bake` runs in a child process, timed by wall clock, with its
peak resident set (`pipeline.benchmarks.peak_rss`); then `pipeline.benchmarks.relight_memory` opens the cache
in another child and times sphere-light moves and colour edits (median ms) with the relighter's
peak. Caches baked by an earlier run into the same --work folder are reused with their bake
figures (`--no-bake`: only those are measured). Writes OUT/summary.md and OUT/exterior.csv.
With `--keep-earlier` the rows of OUT/exterior.csv this run does not measure stay in the table,
each marked with the command that measured it: a film-size shot bake takes long enough to be run
on its own.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

from pipeline.bake.adapter import cache_bytes
from pipeline.benchmarks import run_in_work
from pipeline.benchmarks.asset_table import size_argument
from pipeline.benchmarks.bench.measure import machine_description
from pipeline.benchmarks.suite_assets import write_exterior_shot
from relight_torch.cache.layer import read_cache_layer
from relight_torch.io.atomic import atomic_path

CAMERA = "/Shot/Cams/Horizon"
KINDS = {"direct": ["--method", "direct"], "shot": []}
STEM = "exterior"
SPHERE_LIGHTS = 16
SESSION = ("open_s", "move_ms", "move_cpu_ms", "colour_ms", "colour_cpu_ms", "peak_rss_gb")
"""The `relight_memory` figures the table keeps."""


@dataclasses.dataclass
class Row:
    """One cache of the shot: its bake (wall s, the child's peak RSS GB, bytes, what the bake chose),
    a session on it (`SESSION`) and the command of the run that measured them."""

    size: str
    kind: str
    bake_s: float
    bake_peak_rss_gb: float
    cache_bytes: int
    choice: str
    session: dict[str, float]
    command: str


def run_child(module: str, arguments: list[str], log: Path) -> tuple[float, float, str]:
    """Run `python -m module arguments` to its end: (wall seconds, its peak RSS in GB, its stdout).

    The child's stderr goes to `log` as it runs: a film-size bake runs for hours, and its log lines
    (what each pilot and the full-size check measured) can be read there while it runs and after.

    Raises:
        RuntimeError: the command failed (its last stderr line before the peak's).
    """
    start = time.perf_counter()
    command = [sys.executable, "-m", "pipeline.benchmarks.peak_rss", module, *arguments]
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("w") as stderr:
        done = subprocess.run(command, stdout=subprocess.PIPE, stderr=stderr, text=True, check=False)
    seconds = time.perf_counter() - start
    *lines, peak = log.read_text().strip().splitlines() or ["(no message)"]
    if done.returncode != 0:
        raise RuntimeError(f"{module} {' '.join(arguments[:1])}: {(lines or ['(no message)'])[-1]}")
    return seconds, float(peak.removeprefix("peak_rss_gb: ")), done.stdout


def _choice(layer: Path) -> str:
    """What the bake chose, from the cache layer's parameters: components, bounces and filtering."""
    description = read_cache_layer(layer)
    parameters = description.parameters
    if "shotComponents" not in parameters:
        return f"supersampling {description.supersampling}"
    return f"{parameters['shotComponents']}, {parameters['shotBounces']} bounces, {parameters['shotFiltering']}"


def _folder(work: Path, size: tuple[int, int], kind: str) -> Path:
    return work / f"{kind}_{size[0]}x{size[1]}"


def baked(work: Path, size: tuple[int, int], kind: str) -> bool:
    """Whether an earlier run left the cache of `kind` at `size` in `work` with its bake figures."""
    folder = _folder(work, size, kind)
    return (folder / f"{STEM}.relight.usda").exists() and (folder / "bake.json").exists()


def bake(shot: Path, size: tuple[int, int], kind: str, work: Path) -> tuple[Path, dict]:
    """The cache of `kind` at `size` in `work` and its bake figures, baked unless `baked`."""
    folder = _folder(work, size, kind)
    layer, figures = folder / f"{STEM}.relight.usda", folder / "bake.json"
    if not baked(work, size, kind):
        arguments = ["bake", str(shot), "--camera", CAMERA, "--out", str(folder), "--stem", STEM]
        arguments += ["--width", str(size[0]), "--height", str(size[1]), *KINDS[kind]]
        seconds, peak, _ = run_child("pipeline.cli", arguments, folder.with_name(folder.name + ".bake.log"))
        with atomic_path(figures) as temporary:
            temporary.write_text(json.dumps({"bake_s": seconds, "bake_peak_rss_gb": peak}))
    return layer, json.loads(figures.read_text())


def measure(shot: Path, size: tuple[int, int], kind: str, work: Path, repeats: int, command: str) -> Row:
    """Bake (or reuse) one cache and time a session on it (`command`: this run's)."""
    layer, figures = bake(shot, size, kind, work)
    arguments = [str(layer), "--repeats", str(repeats)]
    log = _folder(work, size, kind).with_name(f"{kind}_{size[0]}x{size[1]}.session.log")
    _, _, printed = run_child("pipeline.benchmarks.relight_memory", arguments, log)
    session = {}
    for line in printed.splitlines():
        name, _, value = line.partition(": ")
        if name in SESSION:
            session[name] = float(value)
    return Row(
        f"{size[0]}x{size[1]}",
        kind,
        figures["bake_s"],
        figures["bake_peak_rss_gb"],
        cache_bytes(layer),
        _choice(layer),
        session,
        command,
    )


COLUMNS = ["size", "kind", "bake_s", "bake_peak_rss_gb", "cache_bytes", "choice", *SESSION, "command"]


def write_rows(path: Path, rows: list[Row]) -> None:
    """`rows` as CSV at `path` (`COLUMNS`), atomically."""
    with atomic_path(path) as temporary, temporary.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(COLUMNS)
        for row in rows:
            figures = [f"{row.bake_s:.1f}", f"{row.bake_peak_rss_gb:.3f}", row.cache_bytes, row.choice]
            writer.writerow(
                [row.size, row.kind, *figures, *(f"{row.session[name]:.3f}" for name in SESSION), row.command]
            )


def read_rows(path: Path) -> list[Row]:
    """The rows `write_rows` wrote at `path`; none when there is no such file."""
    if not path.exists():
        return []
    with path.open(newline="") as handle:
        return [
            Row(
                line["size"],
                line["kind"],
                float(line["bake_s"]),
                float(line["bake_peak_rss_gb"]),
                int(line["cache_bytes"]),
                line["choice"],
                {name: float(line[name]) for name in SESSION},
                line["command"],
            )
            for line in csv.DictReader(handle)
        ]


FORMATS = {"open_s": ".1f", "colour_ms": ".1f", "colour_cpu_ms": ".1f", "peak_rss_gb": ".2f"}
"""Digits of the session's figures (others: whole ms)."""


def summary(rows: list[Row], missing: list[str], teapots: int, command: str, load: tuple[float, float]) -> str:
    """The markdown table of `rows` and the `missing` cells (`load`: the 1-minute load average at
    the start and end)."""
    header = ["size", "cache", "bake s", "bake peak RSS GB", "cache MB", "what the bake chose", "open s"]
    header += ["move ms", "move CPU ms", "colour ms", "colour CPU ms", "relighter peak RSS GB"]
    lines = [
        "# The exterior shot at film sizes",
        "",
        f"Generated by `{command}`. The shot: {teapots} instanced and point-instanced Utah teapots on a floor, a",
        "distant light and sixteen sphere lights, open sky in the top half of the frame",
        "(`pipeline.benchmarks.suite_assets.write_exterior_shot`). Bakes and sessions run in their own",
        "processes; each peak RSS is its process's own. A move translates one sphere light (its transport is",
        "traced again), a colour edit rescales it; each is followed by a render (median of the repeats, after",
        "the first frame). The relighter runs at its default memory budget. A cache an earlier run baked keeps",
        "that run's bake figures (on a machine as loaded as it was then).",
        "",
        "| " + " | ".join(header) + " |",
        "|" + "---|" * len(header),
    ]
    earlier = list(dict.fromkeys(row.command for row in rows if row.command != command))
    for row in rows:
        marks = "*" * (earlier.index(row.command) + 1) if row.command in earlier else ""
        cells = [row.size + marks, row.kind, f"{row.bake_s:.0f}", f"{row.bake_peak_rss_gb:.2f}"]
        cells += [f"{row.cache_bytes / 1e6:.0f}", row.choice]
        cells += [format(row.session[name], FORMATS.get(name, ".0f")) for name in SESSION]
        lines.append("| " + " | ".join(cells) + " |")
    for index, other in enumerate(earlier):
        lines += ["", f"{'*' * (index + 1)} Measured by an earlier run (`--keep-earlier`), on its own: `{other}`."]
    if missing:
        lines += ["", f"Not measured (not baked: `--no-bake`): {', '.join(missing)}."]
    machine = f"Machine: {machine_description()}; this run's load average {load[0]:.1f} / {load[1]:.1f}"
    lines += ["", machine + " (1 min, start / end)."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--teapots", type=int, default=1000)
    parser.add_argument("--sizes", type=size_argument, nargs="+", default=[(640, 480), (1920, 1080)], metavar="WxH")
    parser.add_argument("--kinds", nargs="+", default=list(KINDS), choices=list(KINDS))
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--work", type=Path, default=None, help="keep the shot and its caches here")
    parser.add_argument("--out", type=Path, default=Path("docs/bench/exterior"))
    parser.add_argument(
        "--no-bake", action="store_true", help="time sessions on the caches an earlier run left in --work, bake none"
    )
    parser.add_argument(
        "--keep-earlier",
        action="store_true",
        help="keep the rows of OUT/exterior.csv this run does not measure (marked with their command)",
    )
    args = parser.parse_args(argv)
    given = sys.argv[1:] if argv is None else argv
    shown = [a for i, a in enumerate(given) if a != "--work" and (i == 0 or given[i - 1] != "--work")]
    command = " ".join(["python -m pipeline.benchmarks.exterior", *shown])

    def run(work: Path) -> int:
        load = os.getloadavg()[0]
        rows, missing = [], []
        shot = write_exterior_shot(work / "shot", args.teapots, SPHERE_LIGHTS)
        for size in args.sizes:
            for kind in args.kinds:
                if args.no_bake and not baked(work, size, kind):
                    missing.append(f"{size[0]}x{size[1]} {kind}")
                    continue
                rows.append(measure(shot, size, kind, work, args.repeats, command))
                print(rows[-1], flush=True)
        if args.keep_earlier:
            measured = {(row.size, row.kind) for row in rows}
            rows += [row for row in read_rows(args.out / "exterior.csv") if (row.size, row.kind) not in measured]
            kept = {f"{row.size} {row.kind}" for row in rows}
            missing = [cell for cell in missing if cell not in kept]
        rows.sort(key=lambda row: (math.prod(size_argument(row.size)), list(KINDS).index(row.kind)))
        args.out.mkdir(parents=True, exist_ok=True)
        write_rows(args.out / "exterior.csv", rows)
        with atomic_path(args.out / "summary.md") as temporary:
            temporary.write_text(summary(rows, missing, args.teapots, command, (load, os.getloadavg()[0])))
        print(args.out / "summary.md")
        return 0

    return run_in_work(args.work, run)


if __name__ == "__main__":
    raise SystemExit(main())
