"""Reusing a cache an earlier benchmark run baked (`cuts_sweep --reuse`, `multiview_path
--reuse-bake`): bakes at 640 x 480 take minutes, and timing a relighter change needs none."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from relight_torch.cache.layer import read_cache_layer
from relight_torch.errors import RelightError


def reusable_bake(
    layer: Path, method: str, resolution: tuple[int, int], supersampling: int, parameters: Mapping[str, object]
) -> Path | None:
    """`layer` if it is a readable cache of `method` at this (width, height) and supersampling
    whose recorded parameters include `parameters`, else None. Its code version is not compared
    (the bake's code may have changed since); opening it checks it against the shot's inputs."""
    try:
        description = read_cache_layer(layer)
    except (OSError, RelightError):
        return None
    same = (
        description.method == method
        and tuple(description.resolution) == tuple(resolution)
        and description.supersampling == supersampling
        and all(description.parameters.get(key) == value for key, value in parameters.items())
    )
    return layer if same else None
