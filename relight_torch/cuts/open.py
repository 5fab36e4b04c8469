"""Opening a 'cuts' cache (payloads: `pipeline.bake.cuts.bake`) as a `CutsRelighter`."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from relight_torch.cache.load import load_npy
from relight_torch.cuts.cuts import MEAN_LEVELS, Cuts, indirect_scale
from relight_torch.cuts.relighter import CutsCache, CutsRelighter, CutsRelightSettings
from relight_torch.cuts.tree import LightTree
from relight_torch.direct.relighter import open_relighter
from relight_torch.direct.settings import RelightSettings
from relight_torch.errors import RelightError
from relight_torch.indirect_samples import GatherSamples

_POINT_FIELDS = {"position": "Position", "normal": "Normal", "albedo": "Albedo", "emission": "Emission", "area": "Area"}


def open_cuts_relighter(
    path: str | os.PathLike[str],
    device: str | torch.device = "cpu",
    shadows: str = "embree",
    lights_layer: str | os.PathLike[str] | None = None,
    settings: RelightSettings = RelightSettings(),
    cuts_settings: CutsRelightSettings = CutsRelightSettings(),
) -> CutsRelighter:
    """A CutsRelighter for a 'cuts' cache layer (arguments as `open_relighter`).

    Raises:
        RelightError: a payload is missing, corrupt or inconsistent with the others.
    """
    layer_path = Path(path)
    direct = open_relighter(layer_path, device, shadows, lights_layer, settings)
    description = direct.description
    assert description is not None, "open_relighter sets the layer's description"
    dtype = direct.gbuffer.position.dtype

    def load(name: str, tensor_dtype: torch.dtype) -> torch.Tensor:
        array = np.asarray(load_npy(layer_path, description, name))
        return torch.from_numpy(array.astype(np.int64) if tensor_dtype == torch.int64 else array.astype(np.float32)).to(
            device, tensor_dtype
        )

    try:
        leaf_directions = leaf_weights = None
        leaf_points = None
        if description.parameters.get("cutsMode", "env") == "env":
            leaf_directions = load("cutsLeafDirections", dtype)
            leaf_weights = load("cutsLeafWeights", dtype)
            num_leaves = leaf_directions.shape[0]
            scale = 1.0 / MEAN_LEVELS
        else:
            leaf_points = GatherSamples(
                **{field: load(f"cutsLeaf{name}", dtype) for field, name in _POINT_FIELDS.items()},
                object_id=load("cutsLeafObjectId", torch.int64),
            )
            num_leaves = leaf_points.num_gathers
            scale = indirect_scale(num_leaves)
        tree = LightTree.of(num_leaves, device)
        visibility = Cuts(
            load("cutsOffsets", torch.int64), load("cutsNodes", torch.int64), load("cutsMeans", dtype) * scale
        )
        visibility.check(tree)
        cuts = CutsCache(
            tree,
            visibility,
            load("cutsSampleVertices", torch.int64),
            load("cutsSampleWeights", dtype),
            leaf_directions,
            leaf_weights,
            leaf_points,
        )
        if cuts.sample_vertices.numel() and int(cuts.sample_vertices.max()) >= visibility.num_cuts:
            raise ValueError("a sub-sample names a lattice vertex without a cut")
        return CutsRelighter(direct, cuts, cuts_settings)
    except ValueError as error:
        raise RelightError(f"{layer_path}: cuts payloads are malformed ({error})") from None
