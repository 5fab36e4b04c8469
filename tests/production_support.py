"""Helpers of the production tests (tests/test_production*.py): a tiny shot and a bake that SIGKILLs itself.

Run as a script, `python production_support.py KILL_AT -- relight bake arguments...` runs `relight
bake` in this process and sends itself SIGKILL at the point KILL_AT names (or never, for 'none'):

    chunk:K        right after the K-th chunk file of this run is complete
    chunk-write    inside the first chunk write: the temp file written, not yet renamed
    layer-write    inside the cache layer's write: the temp file written, not yet renamed
    cleanup        after the layer is written, before the chunk folders are removed

A self-sent SIGKILL at an exact point stands for a farm's kill at that point: nothing runs after it.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
from pathlib import Path

from pipeline.scenes import SCENES

SIZE = 8
BAKE_OPTIONS = [
    "--width",
    str(SIZE),
    "--height",
    str(SIZE),
    "--supersampling",
    "1",
    "--texture-samples",
    "1",
    "--method",
    "transfer",
    "--gathers",
    "16",
    "--coefficients",
    "8",
    "--bounces",
    "2",
    "--bounce-coefficients",
    "4",
]


def write_shot(directory: Path) -> Path:
    """The bundled Cornell box under `directory`; its root layer."""
    return SCENES["cornell_box"].write(directory)


def bake_arguments(shot: Path, out: Path) -> list[str]:
    """`relight bake` arguments of the small transfer bake the tests kill (2 rows per chunk: many chunks)."""
    return ["bake", str(shot), "--camera", SCENES["cornell_box"].camera, "--out", str(out), *BAKE_OPTIONS]


def _die() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def _arm(kill_at: str) -> None:
    """Patch the bake so that this process SIGKILLs itself at `kill_at`."""
    from pipeline.bake import indirect, scheduler
    from relight_torch.cache import layer

    if kill_at.startswith("chunk:"):
        remaining = [int(kill_at.split(":")[1])]
        real_run_chunk = scheduler.run_chunk

        def run_chunk(*args, **kwargs):
            path = real_run_chunk(*args, **kwargs)
            remaining[0] -= 1
            if remaining[0] == 0:
                _die()
            return path

        scheduler.run_chunk = run_chunk
    elif kill_at in ("chunk-write", "layer-write"):
        module = scheduler if kill_at == "chunk-write" else layer

        @contextlib.contextmanager
        def dies_before_rename(target):
            temp = Path(target).with_name(f".{Path(target).stem}.tmp-{os.getpid()}{Path(target).suffix}")
            yield temp
            assert temp.stat().st_size > 0
            _die()

        module.atomic_path = dies_before_rename
    elif kill_at == "cleanup":
        indirect.shutil.rmtree = lambda *args, **kwargs: _die()
    elif kill_at != "none":
        raise ValueError(f"unknown kill point {kill_at!r}")


def die_inside_the_first_chunk(marker: str) -> None:
    """Make this process (a Dask worker: `client.run`) SIGKILL itself inside the first chunk that any
    worker of the cluster runs, after the chunk's work and before its file is written.

    The first chunk is the one that creates `marker` (exclusively); the dying worker writes its pid
    there. Workers look `run_chunk` up by name when a task arrives, so the patch applies to them.
    """
    from pipeline.bake import scheduler

    real_run_chunk = scheduler.run_chunk

    def run_chunk(compute, spec, chunk_dir, threads=None):
        def compute_then_die(chunk):
            arrays = compute(chunk)
            try:
                descriptor = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            except FileExistsError:
                return arrays
            os.write(descriptor, str(os.getpid()).encode())
            os.close(descriptor)
            _die()

        return real_run_chunk(compute_then_die, spec, chunk_dir, threads)

    scheduler.run_chunk = run_chunk


if __name__ == "__main__":
    from pipeline.cli import main

    _arm(sys.argv[1])
    sys.exit(main(sys.argv[3:]))
