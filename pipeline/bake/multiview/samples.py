"""Importance-weighted surface samples (Kim et al. 2009, eq. 2) and their visibility from a point.

Triangle i is chosen with probability w_i A_i / sum_k w_k A_k, then sampled uniformly. The weight
w_i in [0, 1] is the `relight:importance` attribute (`RelightImportanceAPI` in relight_torch/schemas/schema.usda)
of the triangle's gprim or its nearest ancestor that authors one, 1 where none does. Samples are
one-sided: a sample is seen from the side its triangle's winding faces (outwards for closed
meshes, as USD's right-handed default winding makes it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pxr import Usd

from pipeline.errors import RelightError
from pipeline.scene.types import Scene
from pipeline.tracing import Tracer
from relight_torch.stage import open_stage

IMPORTANCE_ATTRIBUTE = "relight:importance"
MIN_COS = 0.05
"""A sample counts as seen from a point only above this cosine: grazing views cache too little of it."""


@dataclass(frozen=True)
class SurfaceSamples:
    """M points on the surfaces.

    Attributes:
        position: (M, 3) float32 world points.
        normal: (M, 3) float32 unit face normals (the winding's side).
        weight: (M,) float64 importance w in [0, 1] of each sample's triangle.
        object_id: (M,) int32.
    """

    position: np.ndarray
    normal: np.ndarray
    weight: np.ndarray
    object_id: np.ndarray

    @property
    def num_samples(self) -> int:
        return int(self.position.shape[0])

    def subset(self, keep: np.ndarray) -> SurfaceSamples:
        return SurfaceSamples(self.position[keep], self.normal[keep], self.weight[keep], self.object_id[keep])


def object_importance(scene: Scene, stage: Usd.Stage | None = None) -> np.ndarray:
    """(num_objects,) float64 `relight:importance` of each object (see the module docstring).

    Raises:
        RelightError: an authored importance is outside [0, 1].
    """
    stage = stage or open_stage(scene.source)
    found: dict[str, float] = {}

    def importance(path: str) -> float:
        # Instances of a PointInstancer are named '<instancer>[i]/<prototype path>': read the instancer.
        prim_path = path.split("[", 1)[0]
        if prim_path in found:
            return found[prim_path]
        prim = stage.GetPrimAtPath(prim_path)
        value = 1.0
        while prim and not prim.IsPseudoRoot():
            attribute = prim.GetAttribute(IMPORTANCE_ATTRIBUTE)
            if attribute and attribute.HasAuthoredValue():
                value = float(attribute.Get())
                if not 0.0 <= value <= 1.0:
                    raise RelightError(f"{prim.GetPath()}.{IMPORTANCE_ATTRIBUTE} = {value} must be in [0, 1]")
                break
            prim = prim.GetParent()
        found[prim_path] = value
        return value

    return np.array([importance(obj.path) for obj in scene.objects], np.float64)


def sample_surfaces(
    scene: Scene,
    num_samples: int,
    rng: np.random.Generator,
    importance: np.ndarray,
    box: tuple[np.ndarray, np.ndarray] | None = None,
) -> SurfaceSamples:
    """`num_samples` points by eq. 2, restricted to triangles whose centroid lies in `box` (lo, hi).

    Args:
        importance: (num_objects,) weight per object (`object_importance`).

    Raises:
        RelightError: no triangle in the box has a positive weighted area.
    """
    corners = scene.geometry.positions.astype(np.float64)
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    double_area = np.linalg.norm(cross, axis=-1)
    weight = importance[scene.geometry.object_ids] if importance.size else np.ones(len(corners))
    mass = weight * double_area
    if box is not None:
        centroid = corners.mean(axis=1)
        mass = np.where(np.all((centroid >= box[0]) & (centroid <= box[1]), axis=-1), mass, 0.0)
    if not mass.sum() > 0:
        raise RelightError(f"{scene.source}: no surface of positive importance inside the box")
    triangle = rng.choice(len(corners), size=num_samples, p=mass / mass.sum())
    u, v = rng.random(num_samples), rng.random(num_samples)
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    tri = corners[triangle]
    position = tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])
    normal = cross[triangle] / double_area[triangle, None]
    return SurfaceSamples(
        position.astype(np.float32),
        normal.astype(np.float32),
        weight[triangle],
        scene.geometry.object_ids[triangle].astype(np.int32),
    )


def seen_from(tracer: Tracer, samples: SurfaceSamples, point: np.ndarray) -> np.ndarray:
    """(M,) bool: the samples whose front side sees `point` (3,) unoccluded, above `MIN_COS`.

    One shadow ray per facing sample, from the sample (offset off its surface) to the point.
    """
    offset = np.asarray(point, np.float64) - samples.position
    distance = np.linalg.norm(offset, axis=-1)
    direction = offset / np.maximum(distance, 1e-30)[:, None]
    facing = np.einsum("mk,mk->m", direction, samples.normal) > MIN_COS
    seen = np.zeros(samples.num_samples, bool)
    index = np.flatnonzero(facing & (distance > 2 * tracer.epsilon))
    if index.size:
        dirs = direction[index].astype(np.float32)
        origins = tracer.offset_origins(samples.position[index], samples.normal[index], dirs)
        t_far = (distance[index] - tracer.epsilon).astype(np.float32)
        seen[index] = ~tracer.occluded(origins, dirs, t_far)
    return seen
