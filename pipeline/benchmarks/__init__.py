"""Benchmarks behind the `relight bench-*` commands: timings reported, never asserted."""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from pathlib import Path


def run_in_work(work: Path | None, run: Callable[[Path], int]) -> int:
    """`run(work)`; with no `work`, in a temporary directory removed afterwards (a benchmark's
    bakes and references, kept between runs when the user names a folder)."""
    if work is None:
        with tempfile.TemporaryDirectory() as temporary:
            return run(Path(temporary))
    return run(work)
