"""Relighting caches on disk: one USD layer describing payload files (EXR, .npy)."""
