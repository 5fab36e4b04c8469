"""A GBuffer as EXR channels, and back.

Layout (one EXR at the sub-sample resolution, ZIP):
    P.X P.Y P.Z                 FLOAT  world position
    Z                           FLOAT  depth along the view axis
    N.*, Ng.*, tangent.*, bitangent.*   HALF  unit vectors (.X .Y .Z)
    materialId, objectId        UINT   ids (< 2^24)
    coverage                    HALF   1 where a surface was hit, 0 elsewhere
    diffuseColor.R/G/B, emissiveColor.*, specularColor.*, metallic, roughness, clearcoat,
    clearcoatRoughness, ior, opacity, useSpecularWorkflow      HALF (FLOAT where HALF
                                                               overflows)  UsdPreviewSurface inputs

A material channel whose value is the same on every covered sub-sample is not stored: its
value goes into the payload's `constants` (a purely diffuse scene has no specular channels).
Material channels are HALF (11-bit mantissa: 5e-4 relative, finer than 8-bit textures) unless
a value exceeds HALF's range (65504, e.g. a bright emissiveColor), then FLOAT.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.errors import RelightError
from relight_torch.gbuffer import GBuffer
from relight_torch.io.exr import PIXEL_TYPE_NAMES

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


_HALF_MAX = float(np.finfo(np.float16).max)


def _names(layer: str, components: tuple[str, ...]) -> list[str]:
    return [f"{layer}.{c}" for c in components] if components else [layer]


def _columns(values: np.ndarray) -> list[np.ndarray]:
    return [values[:, i] for i in range(values.shape[1])] if values.ndim == 2 else [values]


def gbuffer_to_channels(gbuffer: GBuffer) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Split a GBuffer into (H, W) EXR channels and the constants elided from them."""
    height, width = gbuffer.image_size
    index = gbuffer.pixel_index.cpu().numpy()

    def image(column: np.ndarray, dtype: npt.DTypeLike) -> np.ndarray:
        full = np.zeros(height * width, dtype)
        full[index] = column.astype(dtype)
        return full.reshape(height, width)

    channels = {"coverage": image(np.ones(index.size), np.float16)}
    for layer, name, components, dtype in GEOMETRY_CHANNELS:
        values = getattr(gbuffer, name).cpu().numpy()
        for channel, column in zip(_names(layer, components), _columns(values), strict=True):
            channels[channel] = image(column, dtype)
    constants: dict[str, float] = {}
    for layer, name, components in MATERIAL_CHANNELS:
        values = getattr(gbuffer.params, name).cpu().numpy().astype(np.float32)
        for channel, column in zip(_names(layer, components), _columns(values), strict=True):
            if not column.size:  # nothing covered: every channel is trivially constant
                constants[channel] = 0.0
            elif np.all(column == column[0]):
                constants[channel] = float(column[0])
            else:
                channels[channel] = image(column, material_dtype(column))
    return channels, constants


def material_dtype(column: np.ndarray) -> type:
    """np.float16 for a material channel's (N,) values, np.float32 where HALF would overflow."""
    return np.float32 if np.abs(column).max(initial=0.0) > _HALF_MAX else np.float16


def check_channel_types(types: dict[str, np.dtype], source: str) -> None:
    """Refuse channels whose pixel type is not the layout's (geometry exact; materials HALF or FLOAT).

    Args:
        types: channel name -> numpy dtype (from an EXR header or the decoded arrays).
        source: the file, for messages.

    Raises:
        RelightError: one line naming the channel, its type and the expected one.
    """
    expected: dict[str, tuple[np.dtype[Any], ...]] = {"coverage": (np.dtype(np.float16),)}
    for layer, _, components, dtype in GEOMETRY_CHANNELS:
        expected.update({channel: (np.dtype(dtype),) for channel in _names(layer, components)})
    for layer, _, components in MATERIAL_CHANNELS:
        expected.update(
            {channel: (np.dtype(np.float16), np.dtype(np.float32)) for channel in _names(layer, components)}
        )
    for channel, channel_type in sorted(types.items()):
        if channel not in expected:
            raise RelightError(f"{source}: unexpected deep framebuffer channel {channel}")
        if np.dtype(channel_type) not in expected[channel]:
            names = " or ".join(PIXEL_TYPE_NAMES[d] for d in expected[channel])
            raise RelightError(
                f"{source}: channel {channel} is {PIXEL_TYPE_NAMES.get(np.dtype(channel_type), channel_type)},"
                f" expected {names}"
            )


def gbuffer_from_channels(
    channels: dict[str, np.ndarray], constants: dict[str, float], camera_position: np.ndarray, source: str
) -> GBuffer:
    """Rebuild a GBuffer (CPU tensors) from EXR channels and constants.

    Raises:
        RelightError: a channel is missing (neither stored nor constant), of the wrong pixel type,
            or not finite on a covered sub-sample, or shapes disagree.
    """
    if "coverage" not in channels:
        raise RelightError(f"{source}: deep framebuffer has no coverage channel")
    check_channel_types({name: channel.dtype for name, channel in channels.items()}, source)
    shape = channels["coverage"].shape
    for name, channel in channels.items():
        if channel.shape != shape:
            raise RelightError(f"{source}: channel {name} has shape {channel.shape}, expected {shape}")
    pixel_index = np.flatnonzero(channels["coverage"].reshape(-1) > 0.5)
    for name, channel in sorted(channels.items()):
        num_bad = int(np.count_nonzero(~np.isfinite(channel.reshape(-1)[pixel_index])))
        if num_bad:
            raise RelightError(f"{source}: channel {name} has {num_bad} non-finite covered values")
    for name, value in sorted(constants.items()):
        if not np.isfinite(value):
            raise RelightError(f"{source}: constant channel {name} = {value} is not finite")

    def column(channel: str, dtype: npt.DTypeLike) -> np.ndarray:
        if channel in channels:
            return channels[channel].reshape(-1)[pixel_index].astype(dtype)
        if channel in constants:
            return np.full(pixel_index.size, constants[channel], dtype)
        raise RelightError(f"{source}: deep framebuffer channel {channel} is missing")

    def gather(layer: str, components: tuple[str, ...], dtype: npt.DTypeLike) -> np.ndarray:
        columns = [column(c, dtype) for c in _names(layer, components)]
        return np.stack(columns, axis=-1) if components else columns[0]

    arrays = {
        name: gather(layer, comps, np.float32 if dtype != np.uint32 else np.int32)
        for layer, name, comps, dtype in GEOMETRY_CHANNELS
    }
    material = {name: gather(layer, comps, np.float32) for layer, name, comps in MATERIAL_CHANNELS}
    material["use_specular_workflow"] = material["use_specular_workflow"] > 0.5
    params = PreviewSurfaceParams.from_numpy(material)
    return GBuffer.from_numpy(
        image_size=shape, pixel_index=pixel_index, params=params, camera_position=camera_position, **arrays
    )
