"""Progress bars for long work (tqdm on stderr; silent when stderr is not a terminal unless forced)."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterator

from tqdm import tqdm


@contextlib.contextmanager
def progress_bar(
    description: str, total: int, unit: str = "it", enabled: bool | None = None
) -> Iterator[Callable[[int, int], None]]:
    """Yield `update(done, total)`, which moves a bar to `done` of `total` units.

    Args:
        enabled: show the bar; None shows it when stderr is a terminal.
    """
    show = sys.stderr.isatty() if enabled is None else enabled
    with tqdm(
        total=total, desc=description, unit=unit, unit_scale=True, disable=not show, file=sys.stderr, dynamic_ncols=True
    ) as bar:

        def update(done: int, _total: int) -> None:
            bar.update(done - bar.n)

        yield update
