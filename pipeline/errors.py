"""The one exception type users see.

Anything wrong with the user's input (a file, a prim, a parameter) raises `RelightError` with a
single line naming the culprit. The CLI prints it as `relight: error: <message>` and exits with 2;
library callers catch it like any exception. Bugs stay ordinary exceptions with tracebacks.
"""

import logging

log = logging.getLogger("relight")


class RelightError(Exception):
    """A user-facing error: bad file, prim, parameter or cache. The message is one line."""


def warn(message: str, sink: list[str] | None = None) -> None:
    """Log a one-line warning and, if given, append it to `sink` (e.g. `Scene.warnings`)."""
    log.warning(message)
    if sink is not None:
        sink.append(message)
