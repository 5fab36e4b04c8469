"""Bake time against where the chunks run (docs/DISTRIBUTED.md).

    python -m pipeline.benchmarks.bake_scaling SIZE MODE [MODE...]

MODE is `inprocess` (the default scheduler), `pool2` (a local pool of 2 processes, `--workers 2`)
or `daskN` (a Dask LocalCluster of N single-threaded worker processes on loopback, started before
the clock). Each bakes the Cornell box at SIZE x SIZE (supersampling 2, texture samples 2) with
the transfer method (4096 gathers, 2 bounces, 512 rows per chunk) and the gather method (512
directions, 32 clusters, 128 representatives per chunk), into a fresh temporary folder, and prints
one line of seconds per method.
"""

from __future__ import annotations

import argparse
import contextlib
import tempfile
import time
from pathlib import Path

from pipeline.bake import scheduler
from pipeline.bake.gather.bake import GatherSettings, bake_gather
from pipeline.bake.transfer.bake import TransferSettings, bake_transfer
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES

TRANSFER = TransferSettings(num_gathers=4096, num_bounces=2, rows_per_chunk=512)
GATHER = GatherSettings(num_directions=512, num_clusters=32, representatives_per_chunk=128)


def time_bakes(size: int, mode: str) -> tuple[float, float]:
    """(transfer, gather) bake seconds of the Cornell box at size x size with the chunks run by `mode`."""
    with tempfile.TemporaryDirectory() as directory, contextlib.ExitStack() as stack:
        out = Path(directory)
        scene = load_scene(SCENES["cornell_box"].write(out / "scene"), width=size, height=size)
        camera = find_camera(scene, SCENES["cornell_box"].camera)
        if mode.startswith("dask"):
            import distributed

            cluster = stack.enter_context(
                distributed.LocalCluster(
                    n_workers=int(mode[4:]), threads_per_worker=1, host="127.0.0.1", dashboard_address=None
                )
            )
            chosen = scheduler.Scheduler(address=cluster.scheduler_address, progress=False)
        else:
            chosen = scheduler.Scheduler(workers=int(mode[4:]) if mode.startswith("pool") else None, progress=False)
        stack.enter_context(scheduler.using(chosen))
        start = time.perf_counter()
        bake_transfer(scene, camera, out / "transfer", "cornell", 2, 2, settings=TRANSFER, progress=False)
        middle = time.perf_counter()
        bake_gather(scene, camera, out / "gather", "cornell", 2, 2, settings=GATHER, progress=False)
        return middle - start, time.perf_counter() - middle


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("size", type=int)
    parser.add_argument("modes", nargs="+", metavar="MODE")
    args = parser.parse_args(argv)
    for mode in args.modes:
        transfer, gather = time_bakes(args.size, mode)
        print(
            f"{args.size}x{args.size} {mode}: transfer {transfer:.1f} s, gather {gather:.1f} s, "
            f"total {transfer + gather:.1f} s",
            flush=True,
        )


if __name__ == "__main__":
    main()
