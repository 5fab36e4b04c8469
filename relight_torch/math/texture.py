"""Texture lookups: bilinear filtering with UsdUVTexture's wrap modes, in torch (any device).

Shared by the bake's material evaluation (`pipeline.scene.textures.sample_texture`) and the opacity
lookups of rays and shadow maps (`relight_torch.visibility.opacity`).
"""

from __future__ import annotations

import torch

WRAP_MODES = ("black", "clamp", "repeat", "mirror")


def sample_bilinear(pixels: torch.Tensor, st: torch.Tensor, wrap_s: str, wrap_t: str) -> torch.Tensor:
    """Bilinear texture lookup as UsdUVTexture and Storm define it.

    st (0, 0) is the lower-left corner of the image; texel (i, j) (column i, row j counted from
    the bottom) has its centre at ((i + 0.5) / W, (j + 0.5) / H). The wrap mode is applied to each
    of the four integer texel indices (the OpenGL rule): 'repeat' blends the last and first columns
    at s = 0, 'clamp' and 'mirror' repeat the edge texel, 'black' blends towards zero.

    Args:
        pixels: (H, W, C) texels, row 0 the TOP of the image.
        st: (N, 2) texture coordinates (float64 keeps texel positions exact on large images).
        wrap_s, wrap_t: one of `WRAP_MODES`.

    Returns:
        (N, C) samples, in `pixels`' dtype and device.
    """
    height, width = pixels.shape[:2]
    # Continuous texel coordinates with texel centres at integers; y counts rows from the bottom.
    x = st[:, 0] * width - 0.5
    y = st[:, 1] * height - 0.5
    x0, y0 = torch.floor(x), torch.floor(y)
    fx = (x - x0).to(pixels.dtype)[:, None]
    fy = (y - y0).to(pixels.dtype)[:, None]
    x0, y0 = x0.long(), y0.long()
    sampled = torch.zeros((st.shape[0], pixels.shape[2]), dtype=pixels.dtype, device=pixels.device)
    for dx, weight_x in ((0, 1.0 - fx), (1, fx)):
        column, column_inside = _wrap_indices(x0 + dx, width, wrap_s)
        for dy, weight_y in ((0, 1.0 - fy), (1, fy)):
            row_from_bottom, row_inside = _wrap_indices(y0 + dy, height, wrap_t)
            texels = pixels[height - 1 - row_from_bottom, column]
            sampled += weight_x * weight_y * texels * (column_inside & row_inside).to(pixels.dtype)[:, None]
    return sampled


def _wrap_indices(index: torch.Tensor, size: int, mode: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Wrap integer texel indices into [0, size); (index, inside), inside False only for 'black'
    taps outside the image."""
    if mode == "repeat":
        return torch.remainder(index, size), torch.ones_like(index, dtype=torch.bool)
    if mode == "mirror":
        period = torch.remainder(index, 2 * size)
        return torch.where(period < size, period, 2 * size - 1 - period), torch.ones_like(index, dtype=torch.bool)
    if mode not in ("black", "clamp"):
        raise ValueError(f"wrap mode must be one of {WRAP_MODES}, got '{mode}'")
    inside = (index >= 0) & (index < size)
    return index.clamp(0, size - 1), (inside if mode == "black" else torch.ones_like(inside))
