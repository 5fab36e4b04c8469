"""Visibility by shadow rays, through any ray caster (Embree on the CPU).

The caster needs `occluded(origins, directions, t_far) -> (M,) bool`, `intersect(origins,
directions, t_far)` returning an object with `distance` (M,), and `epsilon` (a scene-scaled ray
offset); `pipeline.tracing.Tracer` and `relight_torch.visibility.embree.EmbreeCaster` both are.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
import torch

from relight_torch.lights.light import Light


class RayCaster(Protocol):
    epsilon: float

    def occluded(self, origins: np.ndarray, directions: np.ndarray, t_far: np.ndarray) -> np.ndarray: ...

    def intersect(self, origins: np.ndarray, directions: np.ndarray, t_far: np.ndarray | None = None): ...


class RayVisibility:
    """Exact visibility: one shadow ray per light sample.

    Args:
        caster: the caster over every occluder.
        shadow_link_caster: the caster over the occluders of a shadow link
            (`embree.ShadowLinkCasters`), for lights with one; None when the occluders' objects
            are unknown (such lights are then refused).
    """

    def __init__(self, caster: RayCaster, shadow_link_caster: Callable[[tuple[str, ...]], RayCaster] | None = None):
        self.caster = caster
        self.shadow_link_caster = shadow_link_caster
        self.num_rays = 0

    def caster_for(self, light: Light) -> RayCaster:
        """The caster over the occluders that shadow `light` (its `shadow_link`)."""
        if light.shadow_link is None:
            return self.caster
        if self.shadow_link_caster is None:
            raise ValueError(f"{light.path}: shadow linking needs the occluders' object ids "
                             f"(re-bake the cache with this version)")
        return self.shadow_link_caster(light.shadow_link)

    def occluder_distance(self, light: Light, points: torch.Tensor, normals: torch.Tensor,
                          directions: torch.Tensor, distances: torch.Tensor) -> torch.Tensor:
        """(N, S) distance to the first occluder (inf where visible); see `Visibility`."""
        caster = self.caster_for(light)
        eps = caster.epsilon
        num_points, num_samples = distances.shape
        # Leave the surface on the side the light sample is on.
        side = torch.sign((directions * normals.unsqueeze(1)).sum(-1, keepdim=True))
        origins = points.unsqueeze(1) + normals.unsqueeze(1) * (side * eps)
        t_far = torch.where(torch.isfinite(distances), distances - 2.0 * eps, torch.full_like(distances, np.inf))
        o = origins.expand(num_points, num_samples, 3).reshape(-1, 3).detach().cpu().numpy().astype(np.float32, copy=False)
        d = directions.reshape(-1, 3).detach().cpu().numpy().astype(np.float32, copy=False)
        t = t_far.reshape(-1).detach().cpu().numpy().astype(np.float32, copy=False)
        live = t > 0
        result = np.full(t.shape, np.inf, np.float32)
        self.num_rays += int(live.sum())
        if light.shadow.distance >= 0.0:
            hits = caster.intersect(o[live], d[live], t[live])
            result[live] = np.where(np.isfinite(hits.distance), hits.distance, np.inf)
        else:
            result[live] = np.where(caster.occluded(o[live], d[live], t[live]), 0.0, np.inf)
        return torch.from_numpy(result).reshape(num_points, num_samples).to(distances.device, distances.dtype)
