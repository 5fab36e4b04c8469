"""Visibility by shadow rays, through any ray caster (Embree on the CPU).

The caster needs `occluded(origins, directions, t_far) -> (M,) bool`, `intersect(origins,
directions, t_far)` returning an object with `distance` (M,), and `epsilon` (a scene-scaled ray
offset); `pipeline.tracing.Tracer` and `relight_torch.visibility.embree.EmbreeCaster` both are.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Protocol

import numpy as np
import torch

from relight_torch.lights.light import Light
from relight_torch.math.frame import dot


class RayCaster(Protocol):
    """Ray queries over a triangle soup (`embree.EmbreeCaster`): `corners` (T, 3, 3) are the
    triangles `intersect`'s triangle ids index."""

    epsilon: float
    corners: np.ndarray

    def offset_origins(self, points: np.ndarray, normals: np.ndarray, directions: np.ndarray) -> np.ndarray: ...

    def occluded(self, origins: np.ndarray, directions: np.ndarray, t_far: np.ndarray) -> np.ndarray: ...

    def intersect(self, origins: np.ndarray, directions: np.ndarray, t_far: np.ndarray | None = None): ...


class RayVisibility:
    """Exact visibility: one shadow ray per light sample. Thread-safe (Embree scenes are).

    Args:
        caster: the caster over every occluder.
        shadow_link_caster: the caster over the occluders of a shadow link
            (`embree.ShadowLinkCasters`), for lights with one; None when the occluders' objects
            are unknown (such lights are then refused).
    """

    def __init__(self, caster: RayCaster, shadow_link_caster: Callable[[tuple[str, ...]], RayCaster] | None = None):
        self.caster = caster
        self.shadow_link_caster = shadow_link_caster
        self.thread_safe = True
        self.num_rays = 0
        self._count_lock = threading.Lock()  # tiles of points query from several threads

    def caster_for(self, light: Light) -> RayCaster:
        """The caster over the occluders that shadow `light` (its `shadow_link`)."""
        if light.shadow_link is None:
            return self.caster
        if self.shadow_link_caster is None:
            raise ValueError(
                f"{light.path}: shadow linking needs the occluders' object ids (re-bake the cache with this version)"
            )
        return self.shadow_link_caster(light.shadow_link)

    def occluder_distance(
        self,
        light: Light,
        points: torch.Tensor,
        normals: torch.Tensor,
        directions: torch.Tensor,
        distances: torch.Tensor,
    ) -> torch.Tensor:
        """(N, S) distance to the first occluder (inf where visible); see `Visibility`.

        The rays go to the caster samples first, in the memory layout `sample_light` returns
        (a transposed (S, N, ...) tensor: no copy); so does the result.
        """
        caster = self.caster_for(light)
        eps = caster.epsilon
        num_points, num_samples = distances.shape
        directions, distances = directions.transpose(0, 1), distances.transpose(0, 1)  # (S, N, ...)
        # Leave the surface on the side the light sample is on.
        side = torch.sign(dot(directions, normals)).unsqueeze(-1)
        origins = points + normals * eps * side
        t_far = torch.where(distances < np.inf, distances - 2.0 * eps, np.inf)  # distances >= 0
        o = _float32_rows(origins.reshape(-1, 3))
        d = _float32_rows(directions.reshape(-1, 3))
        t = _float32_rows(t_far.reshape(-1))
        live = t > 0
        num_live = int(live.sum())
        with self._count_lock:
            self.num_rays += num_live
        if num_live < t.shape[0]:
            o, d, t = o[live], d[live], t[live]
        if light.shadow.distance >= 0.0:
            hits = caster.intersect(o, d, t)
            found = np.where(np.isfinite(hits.distance), hits.distance, np.inf)
        else:
            found = np.where(caster.occluded(o, d, t), np.float32(0.0), np.float32(np.inf))
        if num_live < live.shape[0]:
            result = np.full(live.shape, np.inf, np.float32)
            result[live] = found
        else:
            result = found.astype(np.float32, copy=False)
        by_sample = torch.from_numpy(np.ascontiguousarray(result)).reshape(num_samples, num_points)
        return by_sample.transpose(0, 1).to(distances.device, distances.dtype)


def _float32_rows(values: torch.Tensor) -> np.ndarray:
    """A C-contiguous float32 numpy array of a tensor (a view where it already is one)."""
    return np.ascontiguousarray(values.detach().cpu().numpy(), dtype=np.float32)
