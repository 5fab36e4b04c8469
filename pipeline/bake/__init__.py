"""Bakers: each turns a scene and camera into a relighting cache (see docs/ARCHITECTURE.md)."""
