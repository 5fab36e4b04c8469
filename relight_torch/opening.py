"""`open_cache`: the one entry point that opens any cache for relighting, whatever its method."""

from __future__ import annotations

import os

import torch

from relight_torch.cache.layer import read_cache_layer
from relight_torch.direct.settings import RelightSettings
from relight_torch.methods import relight_method
from relight_torch.protocol import CacheRelighter


def open_cache(
    path: str | os.PathLike[str],
    device: str | torch.device = "cpu",
    shadows: str = "embree",
    lights_layer: str | os.PathLike[str] | None = None,
    settings: RelightSettings = RelightSettings(),
) -> CacheRelighter:
    """The relighter of a cache layer, by the method the layer records (`relight_torch.methods`).

    Args:
        path: `<stem>.relight.usda` written by `relight bake`.
        device: torch device of the relighting kernels.
        shadows: 'embree' (exact shadow rays, CPU) or 'shadowmaps' (torch, any device).
        lights_layer: USD layer of light edits composed over the shot's lights.
        settings: the direct light's sampling settings (every method has a direct part).

    Returns:
        A `CacheRelighter` with the shot's lights. When its method `needs_view` ('multiview') it
        renders nothing until `set_view` (`pipeline.bake.multiview.view.view_points`).

    Raises:
        RelightError: the layer is unreadable, of a method this build lacks, stale or corrupt.
    """
    method = relight_method(read_cache_layer(path).method)
    return method.open(path, device, shadows, lights_layer, settings)
