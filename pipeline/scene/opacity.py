"""A scene's opacity table: which triangles may let rays through, and their opacity maps.

`scene_opacity` turns the materials' UsdPreviewSurface `opacity` inputs (constant or texture),
`opacityThreshold` and `opacityMode` into the `relight_torch.visibility.opacity.OpacityTable` that
the tracer, the reference, the bake and the relighter's shadows all look hits up in.
"""

from __future__ import annotations

import numpy as np
import torch

from pipeline.scene.types import Material, Scene
from relight_torch.visibility.opacity import OpacityMap, OpacityTable

_OUTPUT_CHANNEL = {"rgb": 0, "r": 0, "g": 1, "b": 2, "a": 3}


def material_opacity(material: Material) -> OpacityMap:
    """The opacity map of one material (its opacity input reduced to one texture channel)."""
    opacity = material.opacity
    constant = float(opacity.value[0])
    texture = opacity.texture
    common = dict(threshold=float(material.opacity_threshold), mode=material.opacity_mode)
    if texture is None:
        return OpacityMap(constant, **common)
    channel = _OUTPUT_CHANNEL[texture.output]
    scale, bias = float(texture.scale[channel]), float(texture.bias[channel])
    num_channels = texture.pixels.shape[2]
    if channel == 3 and num_channels in (1, 3):
        # UsdUVTexture's alpha of a grey or RGB image is 1 everywhere.
        return OpacityMap(scale + bias, **common)
    plane = np.ascontiguousarray(_channel_plane(texture.pixels, channel), np.float32)
    return OpacityMap(
        constant,
        texels=torch.from_numpy(plane),
        wrap_s=texture.wrap_s,
        wrap_t=texture.wrap_t,
        scale=scale,
        bias=bias,
        st_from_uv=torch.from_numpy(np.asarray(texture.st_from_uv[:2], np.float64)),
        **common,
    )


def _channel_plane(pixels: np.ndarray, channel: int) -> np.ndarray:
    """(H, W) channel `channel` of RGBA as UsdUVTexture expands (H, W, C) pixels to it
    (`pipeline.scene.textures.expand_to_rgba`: grey fills r, g and b; grey-alpha's alpha is its second)."""
    num_channels = pixels.shape[2]
    if num_channels <= 2:
        return pixels[..., 1] if channel == 3 else pixels[..., 0]
    return pixels[..., channel]


def scene_opacity(scene: Scene) -> OpacityTable | None:
    """The scene's non-opaque triangles and their opacity maps; None when every surface is opaque."""
    maps = [material_opacity(material) for material in scene.materials]
    clear_materials = [index for index, opacity_map in enumerate(maps) if not opacity_map.opaque()]
    if not clear_materials:
        return None
    geometry = scene.geometry
    triangles = np.flatnonzero(np.isin(geometry.material_ids, clear_materials))
    if triangles.size == 0:
        return None
    # Maps renumbered to the materials that are used.
    used, map_index = np.unique(geometry.material_ids[triangles], return_inverse=True)
    return OpacityTable(
        torch.from_numpy(triangles.astype(np.int64)),
        torch.from_numpy(map_index.astype(np.int64)),
        torch.from_numpy(np.ascontiguousarray(geometry.uvs[triangles], np.float32)),
        tuple(maps[index] for index in used),
    )
