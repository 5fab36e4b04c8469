"""The environment mode's per-frame light: each leaf light's share of the dome lights.

A leaf light stands for the directions of its cell (solid angle w). Its value is the dome's
radiance integrated over the cell, estimated from a fixed pattern of `CELL_SAMPLES` directions
spread over a disk of the cell's area around the leaf direction, through the light model
(`relight_torch.lights.emission.emitted_radiance`: texture, rotation, colour, exposure):

    l = w x mean over the pattern of L_dome(direction)

so a texture finer than the leaf spacing is filtered, not point-sampled.
"""

from __future__ import annotations

import math

import torch

from relight_torch.lights.emission import emitted_radiance
from relight_torch.lights.light import Light
from relight_torch.math.frame import orthonormal_basis, to_world

CELL_SAMPLES = 16
"""Directions averaged per leaf cell (a Fibonacci spiral over the cell's disk)."""


def cell_pattern(directions: torch.Tensor, solid_angles: torch.Tensor) -> torch.Tensor:
    """(L, S, 3) unit directions spread over equal-area disks around (L, 3) `directions`."""
    k = torch.arange(CELL_SAMPLES, device=directions.device, dtype=directions.dtype) + 0.5
    radius = torch.sqrt(k / CELL_SAMPLES)
    angle = k * math.pi * (3.0 - math.sqrt(5.0))
    cap = torch.sqrt(solid_angles / math.pi).unsqueeze(-1)  # disk radius (radians, small cells)
    offset = torch.stack((radius * torch.cos(angle), radius * torch.sin(angle)), dim=-1)
    tangent, bitangent = orthonormal_basis(directions)
    local = torch.cat(
        (cap.unsqueeze(-1) * offset, torch.ones_like(offset[..., :1]).expand(directions.shape[0], -1, 1)), dim=-1
    )
    world = to_world(local, tangent.unsqueeze(1), bitangent.unsqueeze(1), directions.unsqueeze(1))
    return torch.nn.functional.normalize(world, dim=-1)


def dome_leaf_light(
    lights: list[Light], pattern: torch.Tensor, solid_angles: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(diffuse, specular) (L, 3) light of every leaf from the given dome lights, for the two BRDF
    lobes: each dome's radiance over the leaf's cell, evaluated once, times its per-lobe multiplier.

    Args:
        lights: dome lights.
        pattern: (L, S, 3) the leaves' cells' directions (`cell_pattern`, made once per cache).
        solid_angles: (L,) the cells' solid angles.
    """
    diffuse = pattern.new_zeros((pattern.shape[0], 3))
    specular = torch.zeros_like(diffuse)
    if not lights:
        return diffuse, specular
    origin = torch.zeros_like(pattern)
    for light in lights:
        if light.diffuse == 0.0 and light.specular == 0.0:
            continue
        radiance = emitted_radiance(light, origin, pattern).mean(dim=1) * solid_angles.unsqueeze(-1)
        diffuse += light.diffuse * radiance
        specular += light.specular * radiance
    return diffuse, specular
