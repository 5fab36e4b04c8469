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

A disc that crosses the edge of its surface (a wall's gather near the floor, a block's near its
top) stands partly for area that does not exist: those points lie behind the floor, in the air or
outside the room, and their share of the gather's area was lost (M applied to unit gather light
gave 0.937 of the exact covered fraction of each gather's cosine-weighted hemisphere on the
Cornell box with 1,024 gathers, every bounce of indirect light 6 % low). `disc_support` therefore
finds, once per bake, which disc points lie on a surface, and the gather's area is spread over
those alone: the disc is clipped to the surface, its total area kept (the gather's cell of the
gather cloud lies on the surface by construction).

What the points still miss lies closer to the receiver than the points' spacing: a receiver a few
millimetres from a wall draws half its light from the wall's first millimetres, which no finite
set of points resolves (with the support, M applied to unit light still gave 0.950 of the exact
value with 1,024 gathers and 0.973 with 4,096, the loss growing with the gather spacing and
concentrated on receivers near edges). The rows the bake writes are therefore normalised
(`normalised_rows`): a row's geometric weights, times the receiver cosines, estimate the
projected solid angle that surfaces cover around the receiver; the same quantity is measured by
`COVERAGE_SIDE`^2 stratified cosine-weighted rays (the fraction that meets the front of a surface,
times pi), and the row is scaled to it. This is the ratio estimator (Cochran 1977, ch. 6) with
constant radiance as its auxiliary variable: exact when the surroundings are uniformly bright
(the white furnace), and elsewhere the light the points miss is given the row's mean radiance
instead of none.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pipeline.bake.transfer.lobe import lobe_rows
from relight_torch.brdf.preview_surface import glossy
from relight_torch.gbuffer import GBuffer
from relight_torch.indirect_samples import GatherSamples
from relight_torch.math.frame import orthonormal_basis, to_local
from relight_torch.math.sampling import concentric_disk, cosine_hemisphere
from relight_torch.shading import reflected_radiance
from relight_torch.visibility.rays import RayCaster

NEAR_RADII = 6.0
"""Receiver-gather pairs closer than this many gather disc radii sqrt(A_g / pi) are integrated over the disc."""
DISC_POINTS = 36
"""Points per gather disc in the near-field integration (a 6 x 6 stratified grid, concentric map)."""
COVERAGE_SIDE = 16
"""Stratified cosine-weighted rays per receiver side of `covered_projected_solid_angle` (16 x 16 = 256)."""
PROBE_RADII = 0.5
"""`disc_support` looks for a surface this many disc radii above and below each disc point."""


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


def disc_points(gathers: GatherSamples, cols: torch.Tensor) -> torch.Tensor:
    """(N, P, 3) the `DISC_POINTS` points of the discs of gathers `cols` (N,)."""
    pattern = _disc_pattern(DISC_POINTS, gathers.position.dtype)
    normal = gathers.normal[cols]
    tangent, bitangent = orthonormal_basis(normal)
    radius = (gathers.area[cols] / math.pi).sqrt()
    offsets = pattern[:, 0, None] * tangent.unsqueeze(1) + pattern[:, 1, None] * bitangent.unsqueeze(1)
    return gathers.position[cols].unsqueeze(1) + radius[:, None, None] * offsets


def disc_support(gathers: GatherSamples, caster: RayCaster) -> torch.Tensor:
    """(G, P) bool: which of each gather's `DISC_POINTS` disc points lie on a surface.

    A point is on a surface when a segment along the gather's normal through it, `PROBE_RADII`
    disc radii to each side, meets one (a curved surface bends away from the tangent disc by
    r^2 / 2R at distance r: the probe reaches it for curvature radii R above the disc's radius).
    A gather none of whose points finds a surface (an object smaller than its disc) keeps its whole
    disc, so that its area is never dropped.
    """
    cols = torch.arange(gathers.num_gathers)
    targets = disc_points(gathers, cols)
    reach = PROBE_RADII * (gathers.area / math.pi).sqrt()
    normal = gathers.normal.unsqueeze(1).expand_as(targets)
    origins = (targets + reach[:, None, None] * normal).reshape(-1, 3).numpy().astype(np.float32)
    directions = (-normal).reshape(-1, 3).numpy().astype(np.float32)
    t_far = (2.0 * reach).repeat_interleave(DISC_POINTS).numpy().astype(np.float32)
    support = torch.from_numpy(caster.occluded(origins, directions, t_far)).reshape(-1, DISC_POINTS)
    return support | ~support.any(dim=1, keepdim=True)


def _disc_transport(
    points: torch.Tensor,
    normals: torch.Tensor,
    gathers: GatherSamples,
    rows: torch.Tensor,
    cols: torch.Tensor,
    caster: RayCaster,
    support: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Near-field pairs integrated over the gather's disc, clipped to its surface.

    Args:
        points, normals: (R, 3) receivers and their receiving-side normals.
        rows, cols: (N,) the pairs (receiver, gather).
        support: (G, P) bool `disc_support`, or None for whole discs (gathers off any surface).

    Returns:
        (wi_world (N, 3) unit, the weighted mean direction to the lit part of the disc (the centre's
        where none is), weight (N,) = sum over the P' disc points on the surface of cos(theta_j)
        (A_g / P') / (r_j^2 + A_g / (P' pi)) V_j cos(theta_x,j) / cos(theta_x), the receiver cosines
        of each point and of the mean direction, so that weight * cos(theta_x) integrates the
        receiver's cosine too).
    """
    normal = gathers.normal[cols]
    targets = disc_points(gathers, cols)
    on_surface = torch.ones(cols.shape[0], DISC_POINTS, dtype=torch.bool) if support is None else support[cols]
    offset = targets - points[rows].unsqueeze(1)
    squared = (offset * offset).sum(-1)
    distance = squared.sqrt()
    wi_points = offset / distance.clamp(min=torch.finfo(points.dtype).tiny).unsqueeze(-1)
    cos_gather = -(wi_points * normal.unsqueeze(1)).sum(-1)
    facing = (wi_points * normals[rows].unsqueeze(1)).sum(-1) > 0
    live = (squared > 0) & (cos_gather > 0) & facing & on_surface
    part = (gathers.area[cols] / on_surface.sum(1)).unsqueeze(1)
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
    points: torch.Tensor,
    normals: torch.Tensor,
    gathers: GatherSamples,
    caster: RayCaster,
    support: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Directions to every gather and the clamped, shadowed geometric term.

    Args:
        points: (R, 3) receiver positions.
        normals: (R, 3) unit normals of the receiving side (rays leave on that side only).
        gathers: the G gathers.
        caster: Embree queries over the scene (`offset_origins`, `occluded`, `epsilon`).
        support: (G, P) bool, the disc points on a surface (`disc_support` over the same scene);
            None integrates whole discs (gathers that stand for isolated discs).

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
        wi_world[rows, cols], weight[rows, cols] = _disc_transport(
            points, normals, gathers, rows, cols, caster, support
        )
    return wi_world, weight


def covered_projected_solid_angle(
    points: torch.Tensor, normals: torch.Tensor, caster: RayCaster, seed: int
) -> torch.Tensor:
    """(R,) the projected solid angle (sr, at most pi) of the directions around each receiver whose
    first hit is the front of a surface (the side its gathers emit from), measured with
    `COVERAGE_SIDE`^2 jittered-stratified cosine-weighted rays.

    Args:
        points: (R, 3) receiver positions; normals: (R, 3) unit receiving-side normals.
        caster: ray queries over the scene (its `corners` give the hit triangles' facing).
        seed: seed of the jitter.
    """
    side = COVERAGE_SIDE
    num_rows = points.shape[0]
    generator = torch.Generator().manual_seed(seed)
    cells = torch.arange(side, dtype=points.dtype)
    grid = torch.stack(torch.meshgrid(cells, cells, indexing="ij"), dim=-1).reshape(-1, 2)
    u = (grid + torch.rand(num_rows, side * side, 2, generator=generator, dtype=points.dtype)) / side
    local, _ = cosine_hemisphere(u)
    tangent, bitangent = orthonormal_basis(normals)
    frame = (tangent.unsqueeze(1), bitangent.unsqueeze(1), normals.unsqueeze(1))
    directions = sum(local[..., k, None] * axis for k, axis in enumerate(frame))
    directions = directions.reshape(-1, 3).numpy().astype(np.float32)
    starts = points.unsqueeze(1).expand(-1, side * side, -1).reshape(-1, 3).numpy().astype(np.float32)
    facing = normals.unsqueeze(1).expand(-1, side * side, -1).reshape(-1, 3).numpy().astype(np.float32)
    triangle = np.asarray(caster.intersect(caster.offset_origins(starts, facing, directions), directions).triangle_id)
    hit = triangle >= 0
    corners = caster.corners[triangle[hit]]
    face_normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    front = np.zeros(hit.shape[0], dtype=bool)
    front[hit] = np.einsum("nk,nk->n", face_normal, directions[hit]) < 0
    return math.pi * torch.from_numpy(front.reshape(num_rows, side * side)).to(points.dtype).mean(1)


def normalised_rows(
    points: torch.Tensor,
    normals: torch.Tensor,
    gathers: GatherSamples,
    caster: RayCaster,
    support: torch.Tensor | None,
    seed: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """`gather_transport`'s directions and weights, each row's weights scaled so that, times the
    receiver cosines, they sum to the measured `covered_projected_solid_angle` (the module doc's
    ratio estimator). A row without a live gather stays zero.

    Returns:
        (wi_world (R, G, 3), weight (R, G)) as `gather_transport`.
    """
    wi_world, weight = gather_transport(points, normals, gathers, caster, support)
    estimated = (weight * (wi_world * normals.unsqueeze(1)).sum(-1).clamp(min=0.0)).sum(1)
    covered = covered_projected_solid_angle(points, normals, caster, seed)
    scale = torch.where(estimated > 0, covered / estimated.clamp(min=torch.finfo(weight.dtype).tiny), 0.0)
    return wi_world, weight * scale.unsqueeze(1)


def final_gather_rows(
    view: GBuffer, rows: slice, gathers: GatherSamples, caster: RayCaster, support: torch.Tensor | None = None
) -> torch.Tensor:
    """(R, G, 3) rows of F for the view samples `rows` of a CPU GBuffer (`support` as `gather_transport`).

    Glossy view samples (`preview_surface.glossy`) take their specular part from lobe-sampled rays
    (`lobe.lobe_rows`) and their diffuse part from the gathers; the others take the whole BRDF
    towards the gathers.
    """
    position = view.position[rows]
    wi_world, weight = normalised_rows(position, view.geometric_normal[rows], gathers, caster, support, rows.start or 0)
    frame = (view.tangent[rows, None], view.bitangent[rows, None], view.normal[rows, None])
    wo_local = to_local(view.wo_world()[rows], *(f[:, 0] for f in frame))
    wi_local = to_local(wi_world, *frame)
    params = view.params.index(rows)
    block = reflected_radiance(params.with_sample_axis(), wo_local.unsqueeze(1), wi_local, weight.unsqueeze(-1))
    lobed = torch.nonzero(glossy(params), as_tuple=True)[0]
    if lobed.numel():
        picked = params.index(lobed)
        block[lobed] = reflected_radiance(
            picked.with_sample_axis(),
            wo_local[lobed].unsqueeze(1),
            wi_local[lobed],
            weight[lobed].unsqueeze(-1),
            specular_scale=0.0,
        ) + lobe_rows(
            picked,
            position[lobed],
            view.geometric_normal[rows][lobed],
            tuple(f[lobed, 0] for f in frame),
            view.wo_world()[rows][lobed],
            gathers,
            caster,
            rows.start or 0,
        )
    return block


def bounce_rows(
    rows: slice, gathers: GatherSamples, caster: RayCaster, support: torch.Tensor | None = None
) -> torch.Tensor:
    """(R, G, 3) rows of M for the gathers `rows` as diffuse receivers (`support` as `gather_transport`)."""
    normal = gathers.normal[rows]
    wi_world, weight = normalised_rows(gathers.position[rows], normal, gathers, caster, support, rows.start or 0)
    cos_receiver = (wi_world * normal.unsqueeze(1)).sum(-1).clamp(min=0.0)
    return (gathers.albedo[rows] / math.pi).unsqueeze(1) * (cos_receiver * weight).unsqueeze(-1)
