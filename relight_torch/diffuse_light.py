"""Direct light reflected once by diffuse points: the light the indirect methods' gathers re-emit.

Shared by the transfer method (its gather cloud, g_d) and the clustered-gather method (D(g) of
seed 000's equations 2 and 3), through the same light kernels and visibility as the view samples.
"""

from __future__ import annotations

import math

import torch

from relight_torch.light_samples import fixed_light_samples
from relight_torch.lights.emission import sample_light
from relight_torch.lights.light import Light
from relight_torch.lights.shadow import shadow_factor
from relight_torch.visibility import Visibility


def diffuse_radiance(light: Light, position: torch.Tensor, normal: torch.Tensor, albedo: torch.Tensor,
                     visibility: Visibility, num_samples: int, seed: int = 0,
                     chunk_points: int = 1 << 16) -> torch.Tensor:
    """Radiance (G, 3) leaving G diffuse points after one reflection of `light`.

    L = diffuse * albedo / pi * E, E the irradiance from `num_samples` fixed light samples per
    point through the view samples' kernels and visibility (`sample_light`, `occluder_distance`,
    `shadow_factor`), on the side `normal` points to.

    Args:
        light: the light (a unit light to cache per light).
        position: (G, 3) world points; normal: (G, 3) unit receiving normals; albedo: (G, 3).
        visibility: shadow queries.
        num_samples: light samples per point (1 for delta lights).
        seed: seed of the fixed sample pattern.
        chunk_points: points processed together.
    """
    num_points = position.shape[0]
    u = fixed_light_samples(num_points, num_samples, seed, position.device, position.dtype)
    irradiance = torch.zeros_like(position)
    for start in range(0, num_points, chunk_points):
        chunk = slice(start, start + chunk_points)
        sample = sample_light(light, position[chunk], u[chunk])
        distance = visibility.occluder_distance(light, position[chunk], normal[chunk], sample.direction,
                                                sample.distance)
        shadow = shadow_factor(light.shadow, torch.isfinite(distance), distance)
        cosine = (sample.direction * normal[chunk].unsqueeze(1)).sum(-1).clamp(min=0.0)
        irradiance[chunk] = (sample.weight() * shadow * cosine.unsqueeze(-1)).mean(dim=1)
    return light.diffuse * albedo / math.pi * irradiance
