"""The batch baker: USD shot -> relighting caches (see docs/ARCHITECTURE.md)."""

from relight_torch import __version__

__all__ = ["__version__"]
