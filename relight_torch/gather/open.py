"""Opening a 'gather' cache (written by `pipeline.bake.gather.bake`) for relighting."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from relight_torch.cache.load import load_npy
from relight_torch.direct.relighter import open_relighter
from relight_torch.direct.settings import RelightSettings
from relight_torch.errors import RelightError
from relight_torch.gather.relighter import DEFAULT_GATHER_SAMPLES, SET_NAMES, GatherRelighter, GatherSet, SurfacePoints


def open_gather_relighter(
    path: str | os.PathLike[str],
    device: str | torch.device = "cpu",
    shadows: str = "embree",
    lights_layer: str | os.PathLike[str] | None = None,
    settings: RelightSettings = RelightSettings(),
    gather_samples: int = DEFAULT_GATHER_SAMPLES,
) -> GatherRelighter:
    """A GatherRelighter for a 'gather' cache layer (arguments as `open_relighter`; `gather_samples`
    as `GatherRelighter`).

    Raises:
        RelightError: a payload is missing or the sets break their layout's invariants.
    """
    layer_path = Path(path)
    direct = open_relighter(layer_path, device, shadows, lights_layer, settings)
    description = direct.description
    assert description is not None, "open_relighter sets the layer's description"
    dtype = direct.gbuffer.position.dtype
    names = {payload.name for payload in description.payloads}

    def load(name: str) -> torch.Tensor:
        return torch.from_numpy(np.array(load_npy(layer_path, description, name))).to(device)

    try:
        points = SurfacePoints(
            load("gatherPosition"), load("gatherNormal"), load("gatherAlbedo"), object_id=load("gatherObject")
        ).to(device, dtype)
        sets = {
            lobe: GatherSet(
                **{
                    field: load(f"{lobe}{field.capitalize()}")
                    for field in ("index", "weight", "offsets", "neighbours", "rbf")
                }
            ).to(device, dtype)
            for lobe in SET_NAMES
            if f"{lobe}Offsets" in names
        }
        return GatherRelighter(direct, points, sets, load("viewPixels"), load("viewAlbedo").to(dtype), gather_samples)
    except ValueError as error:
        raise RelightError(f"{layer_path}: {error}") from None
