"""Warps from the unit square to disks, hemispheres, spheres and cones, with their densities;
scrambled Sobol sequences; and a midpoint quadrature of the hemisphere.

Every warp takes u (..., 2) uniform in [0, 1)^2 and returns (point, pdf) with the pdf in the
measure of the target (area for the disk, solid angle for directions). Hemispheres are around
+z of the local frame. Each warp has a `*_pdf` twin evaluating the density of any direction.
"""

from __future__ import annotations

import math

import torch


def concentric_disk(u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Shirley-Chiu concentric map of the square onto the unit disk (area preserving).

    Args:
        u: (..., 2) uniform numbers in [0, 1).

    Returns:
        point (..., 2) in the unit disk and its area density 1/pi (...).
    """
    offset = 2.0 * u - 1.0
    ox, oy = offset.unbind(-1)
    x_major = ox.abs() > oy.abs()
    tiny = torch.finfo(u.dtype).tiny
    safe_ox = torch.where(ox.abs() > tiny, ox, torch.ones_like(ox))
    safe_oy = torch.where(oy.abs() > tiny, oy, torch.ones_like(oy))
    radius = torch.where(x_major, ox, oy)
    angle = torch.where(x_major, (math.pi / 4.0) * (oy / safe_ox), math.pi / 2.0 - (math.pi / 4.0) * (ox / safe_oy))
    point = torch.stack((radius * torch.cos(angle), radius * torch.sin(angle)), dim=-1)
    return point, torch.full_like(ox, 1.0 / math.pi)


def cosine_hemisphere(u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Cosine-weighted hemisphere (Malley's method over the concentric disk).

    Args:
        u: (..., 2) uniform numbers in [0, 1).

    Returns:
        direction (..., 3) unit with z >= 0, and its density cos(theta)/pi (...).
    """
    disk, _ = concentric_disk(u)
    z = torch.sqrt((1.0 - (disk * disk).sum(-1)).clamp_min(0.0))
    direction = torch.cat((disk, z.unsqueeze(-1)), dim=-1)
    return direction, cosine_hemisphere_pdf(direction)


def cosine_hemisphere_pdf(direction: torch.Tensor) -> torch.Tensor:
    """Density of `cosine_hemisphere`: max(0, z)/pi for directions (..., 3); returns (...)."""
    return direction[..., 2].clamp_min(0.0) / math.pi


def power_cosine_hemisphere(u: torch.Tensor, exponent: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Hemisphere with density (e + 1)/(2 pi) cos^e(theta): the Phong lobe warp.

    Args:
        u: (..., 2) uniform numbers in [0, 1).
        exponent: (...) e >= 0 (e = 0 is the uniform hemisphere, e = 1 the cosine one).

    Returns:
        direction (..., 3) unit with z >= 0, and its density (...).
    """
    cos_theta = (1.0 - u[..., 0]) ** (1.0 / (exponent + 1.0))
    sin_theta = torch.sqrt((1.0 - cos_theta * cos_theta).clamp_min(0.0))
    phi = 2.0 * math.pi * u[..., 1]
    direction = torch.stack((sin_theta * torch.cos(phi), sin_theta * torch.sin(phi), cos_theta), dim=-1)
    return direction, power_cosine_pdf(cos_theta, exponent)


def power_cosine_pdf(cos_theta: torch.Tensor, exponent: torch.Tensor) -> torch.Tensor:
    """Density of `power_cosine_hemisphere` at a direction of cosine cos_theta (...); 0 below."""
    density = (exponent + 1.0) / (2.0 * math.pi) * cos_theta.clamp_min(0.0) ** exponent
    return torch.where(cos_theta > 0, density, 0.0)


def uniform_hemisphere(u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Uniform directions on the +z hemisphere; density 1/(2 pi). u (..., 2) -> ((..., 3), (...))."""
    return _uniform_zone(u, torch.zeros_like(u[..., 0]))


def uniform_hemisphere_pdf(direction: torch.Tensor) -> torch.Tensor:
    """Density of `uniform_hemisphere` for directions (..., 3): 1/(2 pi) above, 0 below."""
    z = direction[..., 2]
    return torch.where(z >= 0, torch.full_like(z, 0.5 / math.pi), 0.0)


def uniform_sphere(u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Uniform directions on the sphere; density 1/(4 pi). u (..., 2) -> ((..., 3), (...))."""
    return _uniform_zone(u, torch.full_like(u[..., 0], -1.0))


def uniform_sphere_pdf(direction: torch.Tensor) -> torch.Tensor:
    """Density of `uniform_sphere`: 1/(4 pi) for every direction (..., 3); returns (...)."""
    return torch.full_like(direction[..., 0], 0.25 / math.pi)


def uniform_cone(u: torch.Tensor, cos_theta_max: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Uniform directions in the cone around +z of half-angle acos(cos_theta_max).

    Args:
        u: (..., 2) uniform numbers in [0, 1).
        cos_theta_max: (...) cosine of the half-angle, in [-1, 1).

    Returns:
        direction (..., 3) unit and its density 1/(2 pi (1 - cos_theta_max)) (...).
    """
    return _uniform_zone(u, cos_theta_max)


def uniform_cone_pdf(direction: torch.Tensor, cos_theta_max: torch.Tensor) -> torch.Tensor:
    """Density of `uniform_cone` at directions (..., 3): constant inside the cone, 0 outside."""
    z = direction[..., 2]
    density = 1.0 / (2.0 * math.pi * (1.0 - cos_theta_max))
    return torch.where(z >= cos_theta_max, density * torch.ones_like(z), 0.0)


def _uniform_zone(u: torch.Tensor, cos_theta_min: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    # Archimedes: z uniform in [cos_theta_min, 1] is uniform in solid angle on the zone above it.
    cos_theta = 1.0 - u[..., 0] * (1.0 - cos_theta_min)
    sin_theta = torch.sqrt((1.0 - cos_theta * cos_theta).clamp_min(0.0))
    phi = 2.0 * math.pi * u[..., 1]
    direction = torch.stack((sin_theta * torch.cos(phi), sin_theta * torch.sin(phi), cos_theta), dim=-1)
    density = torch.ones_like(cos_theta) / (2.0 * math.pi * (1.0 - cos_theta_min))
    return direction, density


def sobol(
    num_points: int,
    dim: int,
    seed: int = 0,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Owen-scrambled Sobol points (torch.quasirandom.SobolEngine), the same for the same seed.

    Args:
        num_points: number of points; powers of two keep the sequence balanced.
        dim: dimensions per point (<= 21201).
        seed: scrambling seed.
        device, dtype: of the result.

    Returns:
        (num_points, dim) numbers in [0, 1).
    """
    engine = torch.quasirandom.SobolEngine(  # type: ignore[no-untyped-call]  # unannotated in torch
        dimension=dim, scramble=True, seed=seed
    )
    points = engine.draw(num_points, dtype=torch.float64)
    # Rounding a float64 point just below 1 to float32 can give exactly 1; keep the half-open range.
    points = points.to(dtype).clamp_max(1.0 - torch.finfo(dtype).eps / 2)
    return points.to(device)


def hemisphere_quadrature(
    num_theta: int, num_phi: int, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
) -> tuple[torch.Tensor, torch.Tensor]:
    """Midpoint rule over the +z hemisphere on a (theta, phi) grid.

    `(f(directions) * weights).sum()` approximates the integral of f over the hemisphere in
    solid angle; the weights sum to 2 pi up to O(1/num_theta^2).

    Args:
        num_theta, num_phi: cells along theta in [0, pi/2] and phi in [0, 2 pi).
        device, dtype: of the results.

    Returns:
        directions (num_theta * num_phi, 3) unit cell centres and weights (num_theta * num_phi,)
        in sr.
    """
    d_theta = 0.5 * math.pi / num_theta
    d_phi = 2.0 * math.pi / num_phi
    theta = (torch.arange(num_theta, device=device, dtype=dtype) + 0.5) * d_theta
    phi = (torch.arange(num_phi, device=device, dtype=dtype) + 0.5) * d_phi
    theta, phi = torch.meshgrid(theta, phi, indexing="ij")
    sin_theta = torch.sin(theta)
    directions = torch.stack((sin_theta * torch.cos(phi), sin_theta * torch.sin(phi), torch.cos(theta)), dim=-1)
    weights = sin_theta * d_theta * d_phi
    return directions.reshape(-1, 3), weights.reshape(-1)
