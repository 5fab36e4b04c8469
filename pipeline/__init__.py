"""The batch baker: USD shot -> relighting caches (see docs/ARCHITECTURE.md)."""

__version__ = "0.1.0"
