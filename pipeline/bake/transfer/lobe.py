"""F rows of glossy view samples: the specular lobe sampled, its rays traced, their hits read off the gathers.

A row of F built from the gathers (`rows.final_gather_rows`) evaluates the view sample's BRDF towards
each gather disc: a matte lobe sees hundreds of gathers, but a narrow specular lobe falls between them
(on the glossy scene's gold sphere, roughness 0.2, the lobe's solid angle holds a few of 4,096 gathers),
so the reflection of the lit room in a glossy surface comes out as a few blotches. For glossy view
samples (`preview_surface.glossy`: roughness, or a clearcoat's, below 0.5) the row is split by lobe
(as `preview_surface.split`):

- the diffuse part keeps the gather row (the BRDF with its specular part left out);
- the specular and clearcoat part is integrated by Monte Carlo over the lobe: `LOBE_SIDE`^2 jittered-
  stratified directions drawn from those lobes alone (`preview_surface.sample(..., diffuse=False)`),
  each ray traced to the first surface it meets, whose outgoing radiance is the gathers' there
  (`hit_gathers`: a kernel over the nearest gathers on that surface, facing the ray). Each sample adds
  f_s(wo, wi) cos(theta_i) / pdf(wi) / N times its gathers' weights to the row.

Rays that leave the scene add nothing: what they see is a light (a dome), which the direct part
carries. The gathers' radiance is diffuse re-emission (`gather_cloud.reemitted_albedo`), so a glossy
surface seen in a mirror shows its energy, not its own highlight, as everywhere in the transfer method.

The threshold is measured (glossy scene under its dome layer, 96 x 72, 4,096 gathers, 200 coefficients,
2 bounces, against 256-path references; indirect relMSE per roughness class, gather rows -> lobe rows):
below 0.175: 0.168 -> 0.022, 0.25-0.35: 0.296 -> 0.019, 0.35-0.5: 0.096 -> 0.027 (shot lights); the
aluminium at 0.7 went 0.049 -> 0.055 with the lobe sampled there too: from 0.5 up the gathers already
resolve the lobe and 64 directions are the noisier estimate.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree

from relight_torch.brdf import preview_surface
from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.indirect_samples import GatherSamples
from relight_torch.math.frame import to_local, to_world
from relight_torch.visibility.rays import RayCaster

LOBE_SIDE = 8
"""Stratified lobe directions per glossy view sample and side (8 x 8 = 64)."""
LOOKUP_GATHERS = 8
"""Nearest gathers `hit_gathers` considers per hit."""
LOOKUP_COSINE = 0.5
"""A gather stands for a hit only where their normals agree to this cosine (60 degrees): the same
surface, not the wall across a corner."""
LOOKUP_RADII = 4.0
"""... and within this many of its disc radii sqrt(A_g / pi) of the hit."""


def hit_gathers(
    gathers: GatherSamples,
    tree: cKDTree,
    position: np.ndarray,
    normal: np.ndarray,
    direction: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Which gathers give the radiance leaving each hit towards its ray's origin, and how much each.

    The `LOOKUP_GATHERS` nearest gathers, kept where their normal agrees with the hit's
    (`LOOKUP_COSINE`), faces the ray (they emit on their normal's side only) and lies within
    `LOOKUP_RADII` of its disc radii; weighted 1 / (d^2 + r_g^2) (Shepard's inverse distance, softened
    by the disc radius r_g) and normalised to sum to one. A hit no gather stands for gets all-zero
    weights (its surface is smaller than the gathers' spacing: its light is lost); on the glossy
    scene (4,096 gathers) 0.3 % of the glossy pixels' hits.

    Args:
        gathers: the G gathers (CPU).
        tree: a `cKDTree` of `gathers.position`.
        position, normal: (N, 3) hit points and their unit geometric normals.
        direction: (N, 3) unit ray directions (towards the hit).

    Returns:
        (index (N, K) int64 gather ids, weight (N, K) float32), K = min(`LOOKUP_GATHERS`, G).
    """
    k = min(LOOKUP_GATHERS, gathers.num_gathers)
    distance, index = tree.query(position, k=k)
    distance, index = distance.reshape(-1, k), index.reshape(-1, k)
    gather_normal = gathers.normal.numpy()[index]
    radius_squared = gathers.area.numpy()[index] / math.pi
    facing = np.einsum("nkc,nc->nk", gather_normal, direction) < 0
    same = np.einsum("nkc,nc->nk", gather_normal, normal) > LOOKUP_COSINE
    near = distance * distance < LOOKUP_RADII * LOOKUP_RADII * radius_squared
    weight = np.where(facing & same & near, 1.0 / (distance * distance + radius_squared), 0.0)
    total = weight.sum(1, keepdims=True)
    weight = np.divide(weight, total, out=np.zeros_like(weight), where=total > 0)
    return index.astype(np.int64), weight.astype(np.float32)


def lobe_rows(
    params: PreviewSurfaceParams,
    position: torch.Tensor,
    geometric_normal: torch.Tensor,
    frame: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    wo_world: torch.Tensor,
    gathers: GatherSamples,
    caster: RayCaster,
    seed: int,
) -> torch.Tensor:
    """(R, G, 3) the specular and clearcoat part of R view samples' F rows, by lobe sampling (module doc).

    Args:
        params: the R view samples' materials.
        position, geometric_normal: (R, 3) their points and unit geometric normals (the side the
            camera sees).
        frame: (tangent, bitangent, normal), each (R, 3), their shading frames.
        wo_world: (R, 3) unit directions to the camera.
        gathers: the G gathers (CPU).
        caster: ray queries over the scene (`offset_origins`, `intersect`, `corners`).
        seed: seed of the directions' jitter.
    """
    num_rows, num_gathers = position.shape[0], gathers.num_gathers
    rows = torch.zeros(num_rows, num_gathers, 3, dtype=position.dtype)
    if num_rows == 0:
        return rows
    side, dtype = LOBE_SIDE, position.dtype
    num_samples = side * side
    generator = torch.Generator().manual_seed(seed)
    cells = torch.arange(side, dtype=dtype)
    grid = torch.stack(torch.meshgrid(cells, cells, indexing="ij"), dim=-1).reshape(-1, 2)
    u = ((grid + torch.rand(num_rows, num_samples, 2, generator=generator, dtype=dtype)) / side).clamp(max=1 - 1e-6)
    tangent, bitangent, normal = (axis.unsqueeze(1) for axis in frame)
    wo_local = to_local(wo_world, *frame).unsqueeze(1).expand(-1, num_samples, -1)
    samples = params.with_sample_axis()
    wi_local, pdf = preview_surface.sample(samples, wo_local, u, diffuse=False)
    _, specular = preview_surface.split(samples, wo_local, wi_local)
    # f_s cos / pdf / N: the lobe's Monte Carlo weight of each direction (zero for lost samples).
    scale = wi_local[..., 2].clamp(min=0.0) / pdf.clamp(min=torch.finfo(dtype).tiny) / num_samples
    weight = specular * scale.unsqueeze(-1)
    weight = torch.where((pdf > 0).unsqueeze(-1), weight, 0.0)
    wi_world = to_world(wi_local, tangent, bitangent, normal)
    # Directions into the surface (a normal map tilts the lobe below the geometric horizon) meet it.
    live = ((wi_world * geometric_normal.unsqueeze(1)).sum(-1) > 0) & (weight.amax(-1) > 0)
    row, sample = torch.nonzero(live, as_tuple=True)
    if row.numel() == 0:
        return rows
    directions = wi_world[row, sample].numpy().astype(np.float32)
    origins = caster.offset_origins(
        position[row].numpy().astype(np.float32), geometric_normal[row].numpy().astype(np.float32), directions
    )
    hits = caster.intersect(origins, directions)
    hit = np.asarray(hits.hit)
    triangle = np.asarray(hits.triangle_id)[hit]
    corners = caster.corners[triangle]
    face_normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    face_normal /= np.maximum(np.linalg.norm(face_normal, axis=1, keepdims=True), 1e-30)
    hit_position = origins[hit] + np.asarray(hits.distance)[hit, None] * directions[hit]
    index, share = hit_gathers(gathers, cKDTree(gathers.position.numpy()), hit_position, face_normal, directions[hit])
    hit_mask = torch.from_numpy(hit)
    # Each hit spreads its direction's weight over its gathers' columns of its row.
    contribution = weight[row, sample][hit_mask].unsqueeze(1) * torch.from_numpy(share).to(dtype).unsqueeze(-1)
    flat = (row[hit_mask].unsqueeze(1) * num_gathers + torch.from_numpy(index)).reshape(-1)
    rows.view(-1, 3).index_add_(0, flat, contribution.reshape(-1, 3))
    return rows
