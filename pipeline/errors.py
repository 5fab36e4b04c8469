"""User-facing errors and warnings for the bake side.

`RelightError` is defined once in `relight_torch.errors` (the lower layer) and re-exported here.
"""

import logging

from relight_torch.errors import RelightError

__all__ = ["RelightError", "warn"]

log = logging.getLogger("relight")


def warn(message: str, sink: list[str] | None = None) -> None:
    """Log a one-line warning and, if given, append it to `sink` (e.g. `Scene.warnings`)."""
    log.warning(message)
    if sink is not None:
        sink.append(message)
