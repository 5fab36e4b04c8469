"""Hemisphere gathers of view representatives, clustered (the clustered-gather paper, equations 2 and 3).

Each representative v shoots N quasi-Monte Carlo directions (one scrambled Sobol set, shifted
per representative by a Cranley-Patterson rotation) importance-sampled by its UsdPreviewSurface
BRDF; each hit g becomes a gather point with its position, receiving normal, diffuse albedo and
weight w = rho cos / (pdf N), so that I(v) ~ sum_j D(g_j) w_j (equation 2). The diffuse set's
weights hold the diffuse lobe divided by v's diffuse albedo (per-pixel albedo is applied at
relight time); the glossy set's hold the specular lobes. The N gathers are then clustered to K
(`relight_torch.gather.clustering`): a cluster's weight is the sum of its members', its normal
and albedo their averages, its position and object the member nearest its mean.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pipeline.scene.types import Scene
from pipeline.shading_points import shading_points
from pipeline.tracing import Tracer
from relight_torch.brdf import preview_surface
from relight_torch.gather.clustering import cluster, cluster_means, features, nearest_members
from relight_torch.gbuffer import GBuffer
from relight_torch.math.frame import to_local, to_world

LOBES = ("diffuse", "glossy")


@dataclass(frozen=True)
class GatherPoints:
    """N gather points for each of B representatives (invalid where the ray missed or w = 0).

    Attributes:
        position, normal, albedo, weight: (B, N, 3) float32.
        object_id: (B, N) int64 object hit (index into `Scene.objects`; 0 where not valid).
        valid: (B, N) bool.
    """

    position: torch.Tensor
    normal: torch.Tensor
    albedo: torch.Tensor
    weight: torch.Tensor
    object_id: torch.Tensor
    valid: torch.Tensor


def gather(
    scene: Scene,
    tracer: Tracer,
    tangents: np.ndarray,
    view: GBuffer,
    samples: torch.Tensor,
    lobe: str,
    directions_u: torch.Tensor,
    shifts: torch.Tensor,
) -> GatherPoints:
    """Trace the hemisphere gathers of the view samples `samples`.

    Args:
        tangents: (T, 3) per-triangle tangents (`pipeline.scene.surface.triangle_tangents`).
        view: the view samples (CPU); samples: (B,) int64 indices into them.
        lobe: 'diffuse' or 'glossy': which part of the BRDF the weights hold.
        directions_u: (N, 2) QMC points in [0, 1)^2, shared by all representatives.
        shifts: (B, 2) per-representative rotations of those points.
    """
    if lobe not in LOBES:
        raise ValueError(f"lobe must be one of {LOBES}, got {lobe!r}")
    num_reps, num_directions = samples.shape[0], directions_u.shape[0]
    frame = tuple(getattr(view, name)[samples].unsqueeze(1) for name in ("tangent", "bitangent", "normal"))
    params = view.params.index(samples).with_sample_axis()
    wo_local = to_local(view.wo_world()[samples], *(f[:, 0] for f in frame)).unsqueeze(1)
    u = torch.remainder(directions_u.unsqueeze(0) + shifts.unsqueeze(1), 1.0)
    wi_local, pdf = preview_surface.sample(params, wo_local.expand(-1, num_directions, -1), u)
    diffuse, specular = preview_surface.split(params, wo_local, wi_local)
    if lobe == "diffuse":
        albedo = preview_surface.diffuse_albedo(view.params.index(samples)).unsqueeze(1)
        rho = torch.where(albedo > 0, diffuse / albedo.clamp(min=1e-12), 0.0)
    else:
        rho = specular
    cosine = wi_local[..., 2].clamp(min=0.0)
    per_direction = torch.where(pdf > 0, cosine / (pdf.clamp(min=1e-30) * num_directions), 0.0)
    weight = rho * per_direction.unsqueeze(-1)
    wi_world = to_world(wi_local, *frame)
    origins = view.position[samples].unsqueeze(1).expand_as(wi_world).reshape(-1, 3).numpy()
    directions = wi_world.reshape(-1, 3).numpy().astype(np.float32)
    geometric = view.geometric_normal[samples].unsqueeze(1).expand_as(wi_world)
    above = (wi_world * geometric).sum(-1) > 0
    hits = tracer.intersect(tracer.offset_origins(origins, geometric.reshape(-1, 3).numpy(), directions), directions)
    points = shading_points(scene, tangents, hits, directions)
    hit = torch.from_numpy(hits.hit).reshape(num_reps, num_directions)
    valid = hit & above & (weight.amax(-1) > 0)

    def scatter(values: np.ndarray | torch.Tensor) -> torch.Tensor:
        full = torch.zeros(num_reps * num_directions, 3)
        full[torch.from_numpy(hits.hit)] = torch.as_tensor(values, dtype=torch.float32)
        return full.reshape(num_reps, num_directions, 3)

    object_id = torch.zeros(num_reps * num_directions, dtype=torch.int64)
    object_id[torch.from_numpy(hits.hit)] = torch.from_numpy(points.object_id.astype(np.int64))
    return GatherPoints(
        position=scatter(points.position),
        normal=scatter(points.normal),
        albedo=scatter(preview_surface.diffuse_albedo(points.params)),
        weight=torch.where(valid.unsqueeze(-1), weight, 0.0).float(),
        object_id=object_id.reshape(num_reps, num_directions),
        valid=valid,
    )


@dataclass(frozen=True)
class ClusteredGathers:
    """Clustered gathers of B representatives, CSR by representative.

    Attributes:
        position, normal, albedo, weight: (G, 3) float32 clustered points, representative-major.
        object: (G,) int32 object id of the member at `position`.
        counts: (B,) int64 clustered points of each representative.
    """

    position: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    weight: np.ndarray
    object: np.ndarray
    counts: np.ndarray


def cluster_gathers(points: GatherPoints, num_clusters: int, position_weight: float) -> ClusteredGathers:
    """Cluster each representative's gathers to at most `num_clusters` points (empty ones dropped)."""
    labels = cluster(features(points.position, points.normal, position_weight), points.valid, num_clusters)
    _, counts = cluster_means(points.weight, points.valid, labels, num_clusters)
    sums = {
        name: cluster_means(getattr(points, name), points.valid, labels, num_clusters)[0]
        for name in ("normal", "albedo", "weight")
    }
    normal = torch.nn.functional.normalize(sums["normal"], dim=-1)
    weight = sums["weight"] * counts.unsqueeze(-1)
    member = nearest_members(points.position, points.valid, labels, num_clusters)
    position = points.position.gather(1, member.clamp(min=0).unsqueeze(-1).expand(-1, -1, 3))
    object_id = points.object_id.gather(1, member.clamp(min=0))
    kept = counts > 0
    return ClusteredGathers(
        position=position[kept].numpy(),
        normal=normal[kept].numpy(),
        albedo=sums["albedo"][kept].numpy(),
        weight=weight[kept].numpy(),
        object=object_id[kept].numpy().astype(np.int32),
        counts=kept.sum(1).numpy().astype(np.int64),
    )
