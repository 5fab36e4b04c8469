"""The one exception type users see.

Anything wrong with the user's input (a file, a prim, a parameter, a cache) raises `RelightError`
with a single line naming the culprit. The CLI prints it as `relight: error: <message>` and exits
with 2; library callers catch it (it is a ValueError). Bugs stay ordinary exceptions.
"""


class RelightError(ValueError):
    """A user-facing error: bad file, prim, parameter or cache. The message is one line."""
