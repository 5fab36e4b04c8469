"""Progress of long work: a tqdm bar on stderr when it is a terminal (or when forced), otherwise a
log line at most once a minute, so that a bake on a farm, its stderr a log file, still says how
far it is and how long it has left."""

from __future__ import annotations

import contextlib
import logging
import sys
import time
from collections.abc import Callable, Iterator

from tqdm import tqdm

log = logging.getLogger(__name__)

# Seconds between two log lines of the same work: work that ends sooner logs nothing.
LOG_INTERVAL_S = 60.0


@contextlib.contextmanager
def progress_bar(
    description: str, total: int, unit: str = "it", enabled: bool | None = None
) -> Iterator[Callable[[int, int], None]]:
    """Yield `update(done, total)`, which moves a bar to `done` of `total` units.

    Args:
        enabled: show the bar; None shows it when stderr is a terminal. Without a bar, progress
            is logged at INFO every `LOG_INTERVAL_S` seconds.
    """
    show = sys.stderr.isatty() if enabled is None else enabled
    with tqdm(
        total=total, desc=description, unit=unit, unit_scale=True, disable=not show, file=sys.stderr, dynamic_ncols=True
    ) as bar:
        start = last_log = time.monotonic()
        first: int | None = None  # the units done before this run (a resumed bake's)

        def update(done: int, _total: int) -> None:
            nonlocal last_log, first
            bar.update(done - bar.n)
            first = done if first is None else first
            now = time.monotonic()
            if show or now - last_log < LOG_INTERVAL_S or not first < done < total:
                return
            last_log = now
            elapsed = now - start
            left = elapsed * (total - done) / (done - first)
            log.info(
                "%s: %d of %d %s (%.0f%%), %s elapsed, about %s left",
                description,
                done,
                total,
                unit,
                100.0 * done / total,
                _duration(elapsed),
                _duration(left),
            )

        yield update


def _duration(seconds: float) -> str:
    """'42 s', '7 min' or '2.3 h'."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"
