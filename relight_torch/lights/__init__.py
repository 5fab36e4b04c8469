"""Lights: the `Light` description (light.py), what it emits and how to sample it (emission.py,
with geometry, shaping, dome and shadow), and its USD form (usd.py)."""
