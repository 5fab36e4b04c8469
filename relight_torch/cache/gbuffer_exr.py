"""A GBuffer as EXR channels, and back.

Layout (one EXR at the sub-sample resolution, ZIP):
    P.X P.Y P.Z                 FLOAT  world position
    Z                           FLOAT  depth along the view axis
    N.*, Ng.*, tangent.*, bitangent.*   HALF  unit vectors (.X .Y .Z)
    materialId, objectId        UINT   ids (< 2^24)
    coverage                    HALF   1 where a surface was hit, 0 elsewhere
    diffuseColor.R/G/B, emissiveColor.*, specularColor.*, metallic, roughness, clearcoat,
    clearcoatRoughness, ior, opacity, useSpecularWorkflow      HALF  UsdPreviewSurface inputs

A material channel whose value is the same on every covered sub-sample is not stored: its
value goes into the payload's `constants` (a purely diffuse scene has no specular channels).
"""

from __future__ import annotations

import numpy as np
import torch

from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.errors import RelightError
from relight_torch.gbuffer import GBuffer

_XYZ = ("X", "Y", "Z")
_RGB = ("R", "G", "B")
# (EXR layer name, GBuffer field, components, numpy dtype)
GEOMETRY_CHANNELS = (
    ("P", "position", _XYZ, np.float32),
    ("Z", "depth", (), np.float32),
    ("N", "normal", _XYZ, np.float16),
    ("Ng", "geometric_normal", _XYZ, np.float16),
    ("tangent", "tangent", _XYZ, np.float16),
    ("bitangent", "bitangent", _XYZ, np.float16),
    ("materialId", "material_id", (), np.uint32),
    ("objectId", "object_id", (), np.uint32),
)
# (EXR layer name, PreviewSurfaceParams field, components)
MATERIAL_CHANNELS = (
    ("diffuseColor", "diffuse_color", _RGB),
    ("emissiveColor", "emissive_color", _RGB),
    ("specularColor", "specular_color", _RGB),
    ("metallic", "metallic", ()),
    ("roughness", "roughness", ()),
    ("clearcoat", "clearcoat", ()),
    ("clearcoatRoughness", "clearcoat_roughness", ()),
    ("ior", "ior", ()),
    ("opacity", "opacity", ()),
    ("useSpecularWorkflow", "use_specular_workflow", ()),
)


def _names(layer: str, components: tuple[str, ...]) -> list[str]:
    return [f"{layer}.{c}" for c in components] if components else [layer]


def _columns(values: np.ndarray) -> list[np.ndarray]:
    return [values[:, i] for i in range(values.shape[1])] if values.ndim == 2 else [values]


def gbuffer_to_channels(gbuffer: GBuffer) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Split a GBuffer into (H, W) EXR channels and the constants elided from them."""
    height, width = gbuffer.image_size
    index = gbuffer.pixel_index.cpu().numpy()

    def image(column: np.ndarray, dtype) -> np.ndarray:
        full = np.zeros(height * width, dtype)
        full[index] = column.astype(dtype)
        return full.reshape(height, width)

    channels = {"coverage": image(np.ones(index.size), np.float16)}
    for layer, name, components, dtype in GEOMETRY_CHANNELS:
        values = getattr(gbuffer, name).cpu().numpy()
        for channel, column in zip(_names(layer, components), _columns(values)):
            channels[channel] = image(column, dtype)
    constants: dict[str, float] = {}
    for layer, name, components in MATERIAL_CHANNELS:
        values = getattr(gbuffer.params, name).cpu().numpy().astype(np.float32)
        for channel, column in zip(_names(layer, components), _columns(values)):
            if column.size and np.all(column == column[0]):
                constants[channel] = float(column[0])
            else:
                channels[channel] = image(column, np.float16)
    return channels, constants


def gbuffer_from_channels(channels: dict[str, np.ndarray], constants: dict[str, float],
                          camera_position: np.ndarray, source: str) -> GBuffer:
    """Rebuild a GBuffer (CPU tensors) from EXR channels and constants.

    Raises:
        RelightError: a channel is missing (neither stored nor constant) or shapes disagree.
    """
    if "coverage" not in channels:
        raise RelightError(f"{source}: deep framebuffer has no coverage channel")
    shape = channels["coverage"].shape
    for name, channel in channels.items():
        if channel.shape != shape:
            raise RelightError(f"{source}: channel {name} has shape {channel.shape}, expected {shape}")
    pixel_index = np.flatnonzero(channels["coverage"].reshape(-1) > 0.5)

    def column(channel: str, dtype) -> np.ndarray:
        if channel in channels:
            return channels[channel].reshape(-1)[pixel_index].astype(dtype)
        if channel in constants:
            return np.full(pixel_index.size, constants[channel], dtype)
        raise RelightError(f"{source}: deep framebuffer channel {channel} is missing")

    def gather(layer: str, components: tuple[str, ...], dtype) -> np.ndarray:
        columns = [column(c, dtype) for c in _names(layer, components)]
        return np.stack(columns, axis=-1) if components else columns[0]

    arrays = {name: gather(layer, comps, np.float32 if dtype != np.uint32 else np.int32)
              for layer, name, comps, dtype in GEOMETRY_CHANNELS}
    material = {name: gather(layer, comps, np.float32) for layer, name, comps in MATERIAL_CHANNELS}
    material["use_specular_workflow"] = material["use_specular_workflow"] > 0.5
    params = PreviewSurfaceParams.from_numpy(material)
    return GBuffer.from_numpy(image_size=shape, pixel_index=pixel_index, params=params,
                              camera_position=camera_position, **arrays)
