"""The first progressive frame's work after each edit kind: CPU ms at the coarsest level, and its PSNR
against the converged frame.

    python -m pipeline.benchmarks.first_frame --shot-cache L --direct-cache L --work DIR [--threads 1] [--repeats 5]

The caches and edits of `pipeline.benchmarks.progressive` (`prepare`, the Cornell box at the caches'
size). Per cache and edit: an untimed edit, then --repeats edits, each from a warm relighter (the rig
before it rendered), its first frame made at the coarsest level (budget 0, a fresh cost model) and
timed by the process's CPU clock (all threads), then refined to the exact frame for the PSNR. With
--threads 1 the CPU ms is the work itself, which a loaded machine disturbs little; prints one
markdown row per cache and edit (median CPU ms, median wall ms, median dB).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from pipeline.benchmarks import run_in_work
from pipeline.benchmarks.progressive import prepare
from relight_torch import open_cache
from relight_torch.metrics import psnr
from relight_torch.progressive import CostModel, progressive_frames

EDITS = ("colour", "shaping", "move", "new light")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shot-cache", type=Path, required=True)
    parser.add_argument("--direct-cache", type=Path, required=True)
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--work", type=Path, help="the scene and the new light's layer (default: temporary)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    return run_in_work(args.work, lambda work: _run(args, work))


def _run(args: argparse.Namespace, work: Path) -> int:
    # `prepare` reads the image size from the arguments only to bake; the caches are given.
    setup = prepare(
        argparse.Namespace(width=0, height=0, shot_cache=args.shot_cache, direct_cache=args.direct_cache), work
    )
    print("| cache | edit | CPU ms | wall ms | dB vs converged |\n|---|---|---|---|---|")
    for label, layer in ((setup.shot_label, setup.shot_layer), ("direct", setup.direct_layer)):
        relighter = open_cache(layer)
        for edit in EDITS:
            cpu_ms, wall_ms, db = [], [], []
            for k in range(args.repeats + 1):
                before, after = setup.rigs[edit](k)
                relighter.set_lights(before)
                relighter.render()
                relighter.set_lights(after)
                cpu, wall = time.process_time(), time.perf_counter()
                frames = progressive_frames(relighter, 0.0, costs=CostModel())
                first = next(frames)
                cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
                last = list(frames)[-1]
                if k:
                    cpu_ms.append(1e3 * cpu)
                    wall_ms.append(1e3 * wall)
                    db.append(psnr(first.image.cpu().numpy(), last.image.cpu().numpy()))
            print(
                f"| {label} | {edit} | {statistics.median(cpu_ms):.1f} | {statistics.median(wall_ms):.1f} | "
                f"{statistics.median(db):.1f} |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
