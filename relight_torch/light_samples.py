"""Fixed light samples per shading point, so the relit image is stable while lights are edited.

Each shading point gets S stratified sample positions in [0, 1)^2 (a sqrt(S) x sqrt(S) jittered
grid, or a scrambled Sobol set when S is not a square), shifted by a per-point Cranley-Patterson
rotation drawn once from a fixed seed. The same u are used for every light and every edit.

How many samples a light gets: `adaptive_sample_count` of its `angular_radius` (small lights
need fewer).
"""

from __future__ import annotations

import math

import torch

from relight_torch.lights.geometry import axis_scales, world_radius
from relight_torch.lights.light import Light, LightKind
from relight_torch.math.sampling import sobol


def sample_pattern(num_samples: int, seed: int = 0) -> torch.Tensor:
    """(S, 2) float64 stratified positions in [0, 1) shared by every point: a sqrt(S) x sqrt(S)
    grid of cell centres, or a scrambled Sobol set when S is not a square."""
    side = math.isqrt(num_samples)
    if side * side == num_samples:
        grid = (torch.arange(side, dtype=torch.float64) + 0.5) / side
        return torch.stack(torch.meshgrid(grid, grid, indexing="ij"), dim=-1).reshape(-1, 2)
    return sobol(num_samples, 2, seed=seed, dtype=torch.float64)


def point_rotations(num_points: int, seed: int = 0) -> torch.Tensor:
    """(N, 2) float64 Cranley-Patterson rotation of each point, drawn from `seed`."""
    return torch.rand((num_points, 2), generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def fixed_light_samples(
    num_points: int,
    num_samples: int,
    seed: int = 0,
    device: torch.device | str = "cpu",
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """(N, S, 2) sample positions in [0, 1), deterministic in (N, S, seed): the pattern shifted by
    each point's rotation, modulo 1.

    Laid out samples first in memory (a transposed (S, N, 2) tensor), the layout `sample_light`
    works in.
    """
    if num_samples < 1:
        raise ValueError(f"num_samples must be >= 1, got {num_samples}")
    pattern, rotation = sample_pattern(num_samples, seed), point_rotations(num_points, seed)
    # One sample at a time: the float64 sums of all S at once were 2-3x the result's size in
    # temporaries (2.6 GB for 4 M points and 16 samples).
    u = torch.empty((num_samples, num_points, 2), device=device, dtype=dtype)
    for k in range(num_samples):
        u[k] = torch.remainder(pattern[k] + rotation, 1.0).clamp_(max=1.0 - 1e-7)
    return u.transpose(0, 1)


def angular_radius(light: Light, points: torch.Tensor) -> float:
    """Largest angular radius (radians) of the light seen from any of the points (N, 3).

    The half-angle of the light's bounding sphere (area lights) or of its cone (distant light)
    from the nearest point; pi / 2 when a point lies inside the bounding sphere; pi for a dome.
    """
    if light.kind is LightKind.DOME:
        return math.pi
    if light.kind is LightKind.DISTANT:
        return min(max(math.radians(light.angle) / 2.0, 0.0), math.pi)
    radius = bounding_radius(light)
    if radius == 0.0 or points.shape[0] == 0:
        return 0.0
    centre = torch.as_tensor(light.world_from_light[:3, 3], device=points.device, dtype=points.dtype)
    nearest = float((points - centre).norm(dim=-1).min())
    return math.asin(radius / nearest) if nearest > radius else math.pi / 2.0


def adaptive_sample_count(max_samples: int, min_samples: int, angle: float, full_angle: float) -> int:
    """Samples per shading point for a light of angular radius `angle` (radians).

    `max_samples` from `full_angle` up (and always when full_angle <= 0); below it, in
    proportion to the solid angle the light subtends, sin^2(angle) / sin^2(full_angle), and at
    least `min_samples`. A small light's penumbrae and highlights are narrow, so few stratified
    samples estimate them with little noise.
    """
    if full_angle <= 0.0 or angle >= full_angle:
        return max_samples
    fraction = (math.sin(angle) / math.sin(full_angle)) ** 2
    return min(max_samples, max(min_samples, math.ceil(max_samples * fraction)))


def bounding_radius(light: Light) -> float:
    """World radius of a sphere around the light's origin that holds its emitting surface."""
    scale_x, scale_y, _ = axis_scales(light)
    if light.kind is LightKind.SPHERE:
        return world_radius(light)
    if light.kind is LightKind.RECT:
        return 0.5 * math.hypot(light.width * scale_x, light.height * scale_y)
    if light.kind is LightKind.DISK:
        return light.radius * max(scale_x, scale_y)
    return math.hypot(0.5 * light.length * scale_x, world_radius(light))
