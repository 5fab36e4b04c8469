"""The point lights of Cheslack-Postava et al. 2008: directions on the sphere (environment mode) or surface points
(indirect mode).

The paper places random points and relaxes them by repulsion; the spherical Fibonacci lattice is
already evenly spread (every point owns an equal-area cell, neighbours at near-constant spacing)
and deterministic, so it stands in for the relaxed set. Each direction carries the solid angle
4 pi / L of its cell.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.bake.gather_cloud import create_gathers
from pipeline.scene.types import Scene


def sphere_directions(num_lights: int) -> tuple[np.ndarray, np.ndarray]:
    """(directions (L, 3) float32 unit world vectors, solid angles (L,) float32 summing to 4 pi)."""
    if num_lights < 1:
        raise ValueError(f"need at least one light direction, got {num_lights}")
    index = np.arange(num_lights, dtype=np.float64) + 0.5
    y = 1.0 - 2.0 * index / num_lights
    radius = np.sqrt(np.clip(1.0 - y * y, 0.0, None))
    phi = index * math.pi * (3.0 - math.sqrt(5.0))
    directions = np.stack((radius * np.cos(phi), y, radius * np.sin(phi)), axis=-1)
    return directions.astype(np.float32), np.full(num_lights, 4.0 * math.pi / num_lights, np.float32)


def surface_points(scene: Scene, num_lights: int) -> dict[str, np.ndarray]:
    """The indirect mode's point lights: the transfer method's gather cloud (divided among the
    surfaces by area, `create_gathers`), by payload name: 'Position', 'Normal', 'Albedo', 'Emission'
    (L, 3) float32, 'Area' (L,) float32, 'ObjectId' (L,) int32.

    Raises:
        ValueError: num_lights is not a power of 4.
    """
    gathers = create_gathers(scene, num_lights)
    return {
        "Position": gathers.position.numpy(),
        "Normal": gathers.normal.numpy(),
        "Albedo": gathers.albedo.numpy(),
        "Emission": gathers.emission.numpy(),
        "Area": gathers.area.numpy(),
        "ObjectId": gathers.object_id.numpy().astype(np.int32),
    }
