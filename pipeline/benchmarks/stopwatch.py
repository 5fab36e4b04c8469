"""The wall and CPU time of timed sections: the one stopwatch the benchmark scripts share."""

from __future__ import annotations

import contextlib
import statistics
import time
from collections.abc import Iterator


class Stopwatch:
    """Seconds of each timed section: wall (`time.perf_counter`) and this process's CPU
    (`time.process_time`, all threads). On a shared machine the wall time is an upper bound; the
    CPU time is the work itself.

    Attributes:
        wall, cpu: one entry per section, in seconds, in the order timed.
    """

    def __init__(self) -> None:
        self.wall: list[float] = []
        self.cpu: list[float] = []

    @contextlib.contextmanager
    def section(self) -> Iterator[None]:
        """Time the body of a `with` block."""
        start, start_cpu = time.perf_counter(), time.process_time()
        yield
        self.wall.append(time.perf_counter() - start)
        self.cpu.append(time.process_time() - start_cpu)

    def median_ms(self) -> tuple[float, float]:
        """(median wall ms, median CPU ms) of the sections timed so far."""
        return 1e3 * statistics.median(self.wall), 1e3 * statistics.median(self.cpu)
