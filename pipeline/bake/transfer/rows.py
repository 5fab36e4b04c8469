"""Rows of the transfer matrices, evaluated analytically (Listing 9-3) with Embree visibility.

Element (receiver x, gather g), with wi the unit direction from x to g and r their distance:

    final gather F:   f_r(x; wo, wi) cos(theta_x) * cos(theta_g) A_g / (r^2 + A_g / pi) * V(x, g)
    one bounce M:     albedo_x / pi  cos(theta_x) * cos(theta_g) A_g / (r^2 + A_g / pi) * V(x, g)

wo is the fixed direction to the camera, so glossy view samples see their gathers through the
full UsdPreviewSurface lobe. The gather emits like a diffuse disc of area A_g on the side of its
normal. `r^2 + A_g / pi` is the chapter's clamp of the 1/r^2 blow-up in corners, chosen so that
the term is the exact form factor of the disc seen on its axis (A / (pi r^2 + A), never above 1);
far from the gather it is A_g / r^2. Shadow rays are traced only where the element is not
already zero (the chapter's `if (!color.isZero())`).

The clamp alone loses light where receivers and gathers meet at an angle (the corners of a room):
the indirect light of the Cornell box was 12 % low with 1,024 gathers and 6 % low with 4,096, the
loss halving with the gather spacing. Pairs closer than `NEAR_RADII` disc radii are therefore
integrated over the gather's disc: `DISC_POINTS` equal-area points, each with its own clamp (of a
disc `DISC_POINTS` times smaller), facing test and shadow ray.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from relight_torch.gbuffer import GBuffer
from relight_torch.indirect_samples import GatherSamples
from relight_torch.math.frame import orthonormal_basis, to_local
from relight_torch.math.sampling import concentric_disk
from relight_torch.shading import reflected_radiance
from relight_torch.visibility.rays import RayCaster

NEAR_RADII = 6.0
"""Receiver-gather pairs closer than this many gather disc radii sqrt(A_g / pi) are integrated over the disc."""
DISC_POINTS = 36
"""Points per gather disc in the near-field integration (a 4 x 4 stratified grid, concentric map)."""


def _disc_pattern(num_points: int, dtype: torch.dtype) -> torch.Tensor:
    """(P, 2) points of equal area on the unit disc: cell centres of a square grid, concentric map."""
    side = math.isqrt(num_points)
    centres = (torch.arange(side, dtype=dtype) + 0.5) / side
    grid = torch.stack(torch.meshgrid(centres, centres, indexing="ij"), dim=-1).reshape(-1, 2)
    return concentric_disk(grid)[0]


def _shadowed(
    caster: RayCaster, points: torch.Tensor, normals: torch.Tensor, wi_world: torch.Tensor, distance: torch.Tensor
) -> torch.Tensor:
    """(N,) bool: the segment from each receiver to its target (N, 3 each; `distance` (N,)) is blocked."""
    directions = wi_world.numpy().astype(np.float32)
    origins = caster.offset_origins(points.numpy().astype(np.float32), normals.numpy().astype(np.float32), directions)
    t_far = (distance.numpy() - 2.0 * caster.epsilon).astype(np.float32)
    return torch.from_numpy(caster.occluded(origins, directions, np.maximum(t_far, 0.0)))


def _disc_transport(
    points: torch.Tensor,
    normals: torch.Tensor,
    gathers: GatherSamples,
    rows: torch.Tensor,
    cols: torch.Tensor,
    caster: RayCaster,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Near-field pairs integrated over the gather's disc.

    Args:
        points, normals: (R, 3) receivers and their receiving-side normals.
        rows, cols: (N,) the pairs (receiver, gather).

    Returns:
        (wi_world (N, 3) unit, the weighted mean direction to the lit part of the disc (the centre's
        where none is), weight (N,) = sum over the disc points of cos(theta_j) (A_g / P) /
        (r_j^2 + A_g / (P pi)) V_j cos(theta_x,j) / cos(theta_x), the receiver cosines of each point
        and of the mean direction, so that weight * cos(theta_x) integrates the receiver's cosine too).
    """
    pattern = _disc_pattern(DISC_POINTS, points.dtype)
    normal = gathers.normal[cols]
    tangent, bitangent = orthonormal_basis(normal)
    radius = (gathers.area[cols] / math.pi).sqrt()
    offsets = pattern[:, 0, None] * tangent.unsqueeze(1) + pattern[:, 1, None] * bitangent.unsqueeze(1)
    targets = gathers.position[cols].unsqueeze(1) + radius[:, None, None] * offsets
    offset = targets - points[rows].unsqueeze(1)
    squared = (offset * offset).sum(-1)
    distance = squared.sqrt()
    wi_points = offset / distance.clamp(min=torch.finfo(points.dtype).tiny).unsqueeze(-1)
    cos_gather = -(wi_points * normal.unsqueeze(1)).sum(-1)
    facing = (wi_points * normals[rows].unsqueeze(1)).sum(-1) > 0
    live = (squared > 0) & (cos_gather > 0) & facing
    part = (gathers.area[cols] / DISC_POINTS).unsqueeze(1)
    weight = torch.where(live, cos_gather * part / (squared + part / math.pi), 0.0)
    pair, point = torch.nonzero(live, as_tuple=True)
    if pair.numel():
        blocked = _shadowed(
            caster, points[rows[pair]], normals[rows[pair]], wi_points[pair, point], distance[pair, point]
        )
        weight[pair[blocked], point[blocked]] = 0.0
    tiny = torch.finfo(points.dtype).tiny
    cos_receiver = (wi_points * normals[rows].unsqueeze(1)).sum(-1)
    mean = (weight.unsqueeze(-1) * wi_points).sum(1)
    mean = torch.where((weight.sum(1) > 0).unsqueeze(-1), mean, gathers.position[cols] - points[rows])
    mean = mean / mean.norm(dim=-1, keepdim=True).clamp(min=tiny)
    # The caller multiplies by the receiver cosine of `mean`: carry each point's own cosine instead.
    cos_mean = (mean * normals[rows]).sum(-1).clamp(min=tiny)
    return mean, (weight * cos_receiver).sum(1) / cos_mean


def gather_transport(
    points: torch.Tensor, normals: torch.Tensor, gathers: GatherSamples, caster: RayCaster
) -> tuple[torch.Tensor, torch.Tensor]:
    """Directions to every gather and the clamped, shadowed geometric term.

    Args:
        points: (R, 3) receiver positions.
        normals: (R, 3) unit normals of the receiving side (rays leave on that side only).
        gathers: the G gathers.
        caster: Embree queries over the scene (`offset_origins`, `occluded`, `epsilon`).

    Returns:
        (wi_world (R, G, 3) unit, weight (R, G) = cos(theta_g) A_g / (r^2 + A_g / pi) V, zero where
        the gather faces away, lies behind the receiver or is hidden; pairs closer than `NEAR_RADII`
        disc radii integrated over the disc, `_disc_transport`).
    """
    offset = gathers.position.unsqueeze(0) - points.unsqueeze(1)
    squared = (offset * offset).sum(-1)
    distance = squared.sqrt()
    wi_world = offset / distance.clamp(min=torch.finfo(points.dtype).tiny).unsqueeze(-1)
    cos_gather = -(wi_world * gathers.normal.unsqueeze(0)).sum(-1)
    facing = (wi_world * normals.unsqueeze(1)).sum(-1) > 0
    near = squared < NEAR_RADII * NEAR_RADII * gathers.area / math.pi
    live = (squared > 0) & (cos_gather > 0) & facing & ~near
    weight = torch.where(live, cos_gather * gathers.area / (squared + gathers.area / math.pi), 0.0)
    rows, cols = torch.nonzero(live, as_tuple=True)
    if rows.numel():
        blocked = _shadowed(caster, points[rows], normals[rows], wi_world[rows, cols], distance[rows, cols])
        weight[rows[blocked], cols[blocked]] = 0.0
    rows, cols = torch.nonzero(near, as_tuple=True)
    if rows.numel():
        wi_world[rows, cols], weight[rows, cols] = _disc_transport(points, normals, gathers, rows, cols, caster)
    return wi_world, weight


def final_gather_rows(view: GBuffer, rows: slice, gathers: GatherSamples, caster: RayCaster) -> torch.Tensor:
    """(R, G, 3) rows of F for the view samples `rows` of a CPU GBuffer."""
    position = view.position[rows]
    wi_world, weight = gather_transport(position, view.geometric_normal[rows], gathers, caster)
    frame = (view.tangent[rows, None], view.bitangent[rows, None], view.normal[rows, None])
    wo_local = to_local(view.wo_world()[rows], *(f[:, 0] for f in frame))
    wi_local = to_local(wi_world, *frame)
    return reflected_radiance(
        view.params.index(rows).with_sample_axis(), wo_local.unsqueeze(1), wi_local, weight.unsqueeze(-1)
    )


def bounce_rows(rows: slice, gathers: GatherSamples, caster: RayCaster) -> torch.Tensor:
    """(R, G, 3) rows of M for the gathers `rows` as diffuse receivers."""
    normal = gathers.normal[rows]
    wi_world, weight = gather_transport(gathers.position[rows], normal, gathers, caster)
    cos_receiver = (wi_world * normal.unsqueeze(1)).sum(-1).clamp(min=0.0)
    return (gathers.albedo[rows] / math.pi).unsqueeze(1) * (cos_receiver * weight).unsqueeze(-1)
