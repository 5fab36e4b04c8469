"""A light's image from its unit images: the colour scale and lobe multipliers (the relighter's
last stage, a multiply), the light-link mask, and the box filter from sub-samples to pixels."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from relight_torch.lights.emission import light_radiance_scale
from relight_torch.lights.light import Light

# Pixels per row when a colour scale is applied (see add_scaled).
_TILE_PIXELS = 1024


def box_filter(image: torch.Tensor, s: int) -> torch.Tensor:
    """The mean of each s x s block of an (H, W, C) image: (H / s, W / s, C).

    Summed as slabs (s rows of W C values, then s runs of C values), which torch's CPU kernels
    stream; `reshape(H / s, s, W / s, s, C).mean((1, 3))`, the same numbers, runs ~10x slower.
    """
    height, width, channels = image.shape
    rows = image.reshape(height // s, s, width * channels)
    total = sum((rows[:, k] for k in range(1, s)), rows[:, 0])
    runs = total.reshape(height // s, width // s, s * channels)
    total = sum((runs[..., k * channels : (k + 1) * channels] for k in range(1, s)), runs[..., :channels])
    return total / (s * s)


def unit_light(light: Light) -> Light:
    """The light with intensity 1, exposure 0, white colour and no colour temperature."""
    return dataclasses.replace(
        light, intensity=1.0, exposure=0.0, color=(1.0, 1.0, 1.0), enable_color_temperature=False
    )


def colour_scale(light: Light) -> np.ndarray:
    """(3,) factor turning the light's unit image into its image (see `relighter`'s module doc)."""
    unit = light_radiance_scale(unit_light(light))
    full = light_radiance_scale(light)
    scale: np.ndarray = np.divide(full, unit, out=np.zeros(3), where=unit != 0)
    return scale


def lobe_scales(light: Light, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """(3,) factors of the light's diffuse and specular unit images (its colour scale times its
    lobe multipliers), on the device and in the dtype of `like`; None for a light that emits nothing."""
    scale = colour_scale(light)
    if not scale.any():
        return None
    diffuse, specular = (
        torch.as_tensor(scale * lobe, device=like.device, dtype=like.dtype) for lobe in (light.diffuse, light.specular)
    )
    return diffuse, specular


def add_scaled(
    total: torch.Tensor,
    images: tuple[torch.Tensor, torch.Tensor],
    scales: tuple[torch.Tensor, torch.Tensor],
    mask: torch.Tensor | None,
    in_place: bool = True,
) -> torch.Tensor:
    """total (N, 3) plus a light's diffuse and specular unit images (N, 3) each times its (3,)
    scale (`lobe_scales`), and times its light-link `mask` (N, 1) when given; a new tensor unless
    `in_place`."""
    diffuse, specular = images
    diffuse_scale, specular_scale = scales
    if mask is not None:
        diffuse_scale, specular_scale = diffuse_scale * mask, specular_scale * mask
    # Without a mask the (3,) scales broadcast along rows of 3: read (N, 3) as rows of k
    # pixels and the scales tiled k times, so that torch's CPU kernels stream long rows.
    k = math.gcd(total.shape[0], _TILE_PIXELS) if mask is None else 1
    shape = (-1, 3 * k)
    if k > 1:
        diffuse, specular = diffuse.reshape(shape), specular.reshape(shape)
        diffuse_scale, specular_scale = diffuse_scale.repeat(k), specular_scale.repeat(k)
    rows = total.view(shape)
    rows = rows.addcmul_(diffuse, diffuse_scale) if in_place else torch.addcmul(rows, diffuse, diffuse_scale)
    return rows.addcmul_(specular, specular_scale).view(total.shape)
