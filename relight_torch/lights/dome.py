"""Dome light lat-long lookups and luminance importance sampling.

Lookup (hdEmbree `_SampleDomeLight`, the OpenEXR lat-long convention), for a unit direction d in
the lookup frame (+Y = top pole): u = 0.5 - atan2(d.x, d.z) / (2 pi), v_from_top = acos(d.y) / pi.
The lookup frame is the light's frame for DomeLight and for DomeLight_1 with poleAxis Y; with
poleAxis Z the top pole is local +Z and longitude 0 points to local -Y (rotation of +90 degrees
about X), per the 26.11 DomeLight_1 schema text. Pixels are looked up nearest, matching the
piecewise-constant sampling density.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from relight_torch.lights.image import ArrayTensorCache, lookup_nearest

REC709_LUMINANCE = (0.2126, 0.7152, 0.0722)


def lookup_from_local(directions_local: torch.Tensor, pole_axis: str) -> torch.Tensor:
    """Light-local unit directions (..., 3) to the lat-long lookup frame (+Y pole) (..., 3)."""
    if pole_axis == "Z":
        x, y, z = directions_local.unbind(-1)
        return torch.stack((x, z, -y), dim=-1)
    return directions_local


def local_from_lookup(directions_lookup: torch.Tensor, pole_axis: str) -> torch.Tensor:
    """Inverse of `lookup_from_local`."""
    if pole_axis == "Z":
        x, y, z = directions_lookup.unbind(-1)
        return torch.stack((x, -z, y), dim=-1)
    return directions_lookup


def latlong_coordinates(directions_lookup: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(u, v_from_top), each (...) in [0, 1], of unit directions (..., 3) in the lookup frame.

    theta = atan2(|(x, z)|, y), not acos(y): near the poles y rounds to 1 in float32 (acos(y) is
    resolved only to 3.5e-4 rad there), while x and z keep their relative precision.
    """
    x, y, z = directions_lookup.unbind(-1)
    u = 0.5 - torch.atan2(x, z) / (2.0 * math.pi)
    return u, torch.atan2(torch.hypot(x, z), y) / math.pi


def latlong_direction(u: torch.Tensor, v_from_top: torch.Tensor) -> torch.Tensor:
    """Inverse of `latlong_coordinates`: unit directions (..., 3) in the lookup frame."""
    theta = v_from_top * math.pi
    longitude = (0.5 - u) * (2.0 * math.pi)
    sin_theta = torch.sin(theta)
    return torch.stack((sin_theta * torch.sin(longitude), torch.cos(theta), sin_theta * torch.cos(longitude)), dim=-1)


@dataclass(frozen=True)
class DomeSampler:
    """Piecewise-constant 2-D distribution over a lat-long image, proportional to luminance x sin(theta).

    Tables are float64 (a 4k map needs more than float32's 24 bits in its CDFs); samples are cast
    to the caller's dtype.

    Attributes:
        pixels: (H, W, 3) image on the device, in the caller's dtype.
        marginal_cdf: (H + 1,) float64 CDF over rows (0 first, 1 last).
        row_cdf: (H, W + 1) float64 CDF over columns within each row.
        flat_row_cdf: (H * W,) float64 row index + row_cdf[:, 1:], increasing: one searchsorted
            finds the column within a chosen row.
        pdf_uv: (H, W) density over the unit square of (u, v_from_top).
    """

    pixels: torch.Tensor
    marginal_cdf: torch.Tensor
    row_cdf: torch.Tensor
    flat_row_cdf: torch.Tensor
    pdf_uv: torch.Tensor

    @staticmethod
    def build(texture: np.ndarray, device: torch.device, dtype: torch.dtype) -> DomeSampler:
        """Precompute the tables for a (H, W, 3) lat-long image (row 0 = top pole)."""
        height, width = texture.shape[:2]
        luminance = np.clip(texture.astype(np.float64) @ np.asarray(REC709_LUMINANCE), 0.0, None)
        sin_theta = np.sin((np.arange(height) + 0.5) / height * math.pi)[:, None]
        weights = luminance * sin_theta
        if weights.sum() <= 0:  # a black dome: any valid density does; take the uniform sphere's
            weights = np.broadcast_to(sin_theta, (height, width)).copy()
        row_sums = weights.sum(axis=1)
        marginal_cdf = np.concatenate(([0.0], np.cumsum(row_sums))) / row_sums.sum()
        row_weights = np.where(row_sums[:, None] > 0, weights, 1.0)
        row_cdf = np.concatenate((np.zeros((height, 1)), np.cumsum(row_weights, axis=1)), axis=1)
        row_cdf /= row_cdf[:, -1:]
        flat_row_cdf = (np.arange(height)[:, None] + row_cdf[:, 1:]).reshape(-1)
        pdf_uv = weights * (height * width / weights.sum())

        def tensor(array: np.ndarray, table_dtype: torch.dtype = torch.float64) -> torch.Tensor:
            return torch.as_tensor(array, device=device, dtype=table_dtype)

        return DomeSampler(
            tensor(texture, dtype), tensor(marginal_cdf), tensor(row_cdf), tensor(flat_row_cdf), tensor(pdf_uv, dtype)
        )

    def sample_uv(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Warp uniform numbers u (..., 2) to (u, v_from_top), each (...), distributed as pdf_uv."""
        height, width = self.pdf_uv.shape
        u = u.to(torch.float64)
        row = torch.searchsorted(self.marginal_cdf[1:], u[..., 0].contiguous(), right=True).clamp_max(height - 1)
        row_start = self.marginal_cdf[row]
        row_fraction = (u[..., 0] - row_start) / (self.marginal_cdf[row + 1] - row_start)
        flat = torch.searchsorted(self.flat_row_cdf, (row + u[..., 1]).contiguous(), right=True)
        col = (flat - row * width).clamp(0, width - 1)
        col_start = self.row_cdf[row, col]
        col_fraction = (u[..., 1] - col_start) / (self.row_cdf[row, col + 1] - col_start)
        sample_u = (col + col_fraction.clamp(0.0, 1.0)) / width
        sample_v = (row + row_fraction.clamp(0.0, 1.0)) / height
        return sample_u.to(self.pixels.dtype), sample_v.to(self.pixels.dtype)

    def radiance(self, directions_lookup: torch.Tensor) -> torch.Tensor:
        """Image value (..., 3) seen along unit directions (..., 3) of the lookup frame."""
        return lookup_nearest(self.pixels, *latlong_coordinates(directions_lookup))

    def pdf(self, directions_lookup: torch.Tensor) -> torch.Tensor:
        """Solid-angle density (...) of the sampled directions: pdf_uv / (2 pi^2 sin theta); 0 at the poles."""
        u, v_from_top = latlong_coordinates(directions_lookup)
        height, width = self.pdf_uv.shape
        col = (u * width).long().clamp(0, width - 1)
        row = (v_from_top * height).long().clamp(0, height - 1)
        # |(x, z)|, not sqrt(1 - y^2), which cancels near the poles in float32 (the
        # sin(theta) Jacobian off by up to 2x in the top and bottom rows).
        sin_theta = torch.hypot(directions_lookup[..., 0], directions_lookup[..., 2])
        density = self.pdf_uv[row, col] / (2.0 * math.pi**2 * sin_theta.clamp_min(torch.finfo(sin_theta.dtype).tiny))
        return torch.where(sin_theta > 0, density, torch.zeros_like(density))


dome_samplers = ArrayTensorCache(DomeSampler.build, max_entries=4)
