"""Opening a 'transfer' cache (payloads: `pipeline.bake.transfer.bake`) as a `TransferRelighter`."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import torch

from relight_torch.cache.layer import CacheDescription
from relight_torch.cache.load import load_npy
from relight_torch.direct.relighter import open_relighter
from relight_torch.direct.settings import RelightSettings
from relight_torch.errors import RelightError
from relight_torch.indirect_samples import GatherSamples, gather_payload_name
from relight_torch.transfer.encoding import PARTS, EncodedRows, decode_rows
from relight_torch.transfer.relighter import TransferRelighter
from relight_torch.transfer.sparse import SparseRows
from relight_torch.upsample import edge_aware_upsampler


def _load(layer_path: Path, description: CacheDescription, name: str) -> torch.Tensor:
    """A .npy payload (checked against the layer) as a CPU tensor."""
    return torch.from_numpy(np.array(load_npy(layer_path, description, name)))


def load_sparse_rows(layer_path: Path, description: CacheDescription, prefix: str, num_columns: int) -> SparseRows:
    """The wavelet rows stored under `prefix` (see `pipeline.bake.transfer.bake`), decoded, checked.

    Raises:
        RelightError: a payload is missing or breaks the layout's invariants.
    """
    parts = [part for part in PARTS if part != "Colour" or int(description.parameters.get("rowColour", 0))]
    arrays = {part: load_npy(layer_path, description, prefix + part) for part in parts}
    rows = decode_rows(EncodedRows.from_arrays(arrays, num_columns))
    try:
        rows.check()
    except ValueError as error:
        raise RelightError(f"{layer_path}: {prefix} rows are malformed ({error})") from None
    return rows


def open_transfer_relighter(
    path: str | os.PathLike[str],
    device: str | torch.device = "cpu",
    shadows: str = "embree",
    lights_layer: str | os.PathLike[str] | None = None,
    settings: RelightSettings = RelightSettings(),
    cull_tolerance: float = 0.0,
) -> TransferRelighter:
    """A TransferRelighter for a 'transfer' cache layer (arguments as `open_relighter`; culling of
    weak wavelet lights as `TransferRelighter`)."""
    layer_path = Path(path)
    direct = open_relighter(layer_path, device, shadows, lights_layer, settings)
    description = direct.description
    assert description is not None, "open_relighter sets the layer's description"
    stored = {payload.name for payload in description.payloads}
    gathers = GatherSamples(
        **{
            field.name: _load(layer_path, description, gather_payload_name(field.name))
            for field in dataclasses.fields(GatherSamples)
            if gather_payload_name(field.name) in stored or field.name != "object_id"
        }
    ).to(device)
    dtype = direct.gbuffer.position.dtype
    final_gather = load_sparse_rows(layer_path, description, "finalGather", gathers.num_gathers).to(device, dtype)
    num_bounces = int(description.parameters["bounces"])
    bounce = (
        load_sparse_rows(layer_path, description, "bounce", gathers.num_gathers).to(device, dtype)
        if num_bounces > 1
        else None
    )
    view_pixels = _load(layer_path, description, "viewPixels").to(device)
    scale = int(description.parameters.get("indirectScale", 1))
    upsampler = None
    if scale > 1:
        upsampler = edge_aware_upsampler(
            direct.gbuffer,
            direct.supersampling,
            scale,
            view_pixels,
            _load(layer_path, description, "viewPosition").to(device),
            _load(layer_path, description, "viewNormal").to(device),
            _load(layer_path, description, "viewObjectId").to(device),
        )
    try:
        return TransferRelighter(
            direct,
            gathers,
            view_pixels,
            final_gather,
            bounce,
            num_bounces,
            upsampler=upsampler,
            cull_tolerance=cull_tolerance,
            indirect_scale=scale,
        )
    except ValueError as error:
        raise RelightError(f"{layer_path}: {error}") from None
