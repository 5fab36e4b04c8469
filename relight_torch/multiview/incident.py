"""The viewer-independent part of direct light at the caching cameras' samples: a camera move traces nothing.

A light's contribution at a point is sum_s f(wo, wi_s) cos_s L_s V_s / (pdf_s S): only the BRDF
f and the cosine (in the shading frame) involve the point's own view or frame; the light samples,
their radiance (shaping and Barzel included), pdf and shadow (ShadowAPI colour) do not. Per light,
`incident_table` traces those once for every sample of the caching cameras' pool (with the same
fixed light samples per caching view as the direct Relighter over that view: `sample_light`,
the visibility's `occluder_distance`, `shadow_factor`, `emission_factor`) and keeps them in G
groups of neighbouring light samples (blocks of the stratified grid):

    W_g = sum_{s in g} L_s V_s shaping_s / (pdf_s S)          (3,) RGB, samples facing the surface only
    D_g = sum_{s in g} mean(L_s V_s shaping_s / (pdf_s S)) wi_s   (3,) the groups' weighted direction

and, for lights with a closed-form unshadowed irradiance, the direct Relighter's ratio-estimator
factor on the diffuse sum (exact over the samples' estimate of it, at the sample's shading normal).
`incident_table` also returns each point's unshadowed W (summed over samples and channels): the
MultiviewRelighter keeps, per caching sample, the fraction of the light reaching it past
occluders, which its edge detection compares between neighbouring caching pixels.
`group_images` shades a new view's points from their blended W, D: the direct BRDF
(`preview_surface.split`, the only BRDF) at the point's own wo and normal, evaluated once per
group at wi_g = D_g / |D_g|:

    (diffuse, specular) = sum_g split(params, wo, wi_g) cos(wi_g) W_g     (diffuse x the ratio)

These are the direct Relighter's unit images (its `_images`, before colour scale and light link),
which the MultiviewRelighter hands to a Relighter over the view (`Relighter.set_unit_images`).
With G = S (one sample per group) this is exactly the Relighter's transport at the caching sample
(a view equal to a caching camera renders as re-tracing it does); fewer groups evaluate the BRDF at
each group's mean direction, which blurs highlights narrower than a group's spread of directions
(sharp lobes under large lights) and costs G / S of the BRDF work.
"""

from __future__ import annotations

import dataclasses
import math

import torch

from relight_torch.brdf import preview_surface
from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.direct.images import unit_light
from relight_torch.light_samples import fixed_light_samples
from relight_torch.lights.emission import sample_light
from relight_torch.lights.geometry import LightFrame
from relight_torch.lights.light import Light
from relight_torch.lights.ratio import analytic_ratio, estimate_weights
from relight_torch.lights.shadow import shadow_factor
from relight_torch.lights.shaping import emission_factor
from relight_torch.math.frame import dot

CHANNELS = 7
"""Columns per group in a table: W (RGB), D (xyz), then the light's ratio-estimator factor on the
diffuse sum (`lights.ratio.analytic_ratio`, as the direct Relighter applies it; 1 for lights
without a closed form), the same in every group."""


def sample_groups(num_samples: int, num_groups: int) -> torch.Tensor:
    """(S,) int64 group of each light sample: g x g blocks of a side x side stratified grid when
    both are squares and g divides side (the `fixed_light_samples` pattern, row-major), else runs
    of consecutive samples. At most S groups."""
    num_groups = max(1, min(num_groups, num_samples))
    side, g = math.isqrt(num_samples), math.isqrt(num_groups)
    index = torch.arange(num_samples)
    if side * side == num_samples and g * g == num_groups and side % g == 0:
        block = side // g
        return (index // side // block) * g + (index % side) // block
    return index * num_groups // num_samples


def pool_light_samples(
    counts: list[int], num_samples: int, seed: int, device: torch.device, dtype: torch.dtype = torch.float32
) -> torch.Tensor:
    """(R, S, 2) fixed light samples of a pool of views with `counts` samples each: each view's
    own `fixed_light_samples(N_k, S, seed)`, those the direct Relighter over that view draws."""
    parts = [fixed_light_samples(n, num_samples, seed, device, dtype) for n in counts if n]
    return torch.cat(parts) if parts else torch.zeros((0, num_samples, 2), device=device, dtype=dtype)


def incident_table(
    light: Light,
    position: torch.Tensor,
    normal: torch.Tensor,
    shading_normal: torch.Tensor,
    u: torch.Tensor,
    visibility,
    num_groups: int,
    chunk_samples: int = 1 << 20,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(P, G, 7) float32 W, D and the diffuse ratio (module docstring) of `light` at P points, and
    (P,) their unshadowed W summed over samples and channels (what edge detection divides by).

    Args:
        light: the light (its colour is ignored: the unit light's table, as the Relighter's transport).
        position, normal, shading_normal: (P, 3) the points, their unit geometric and shading normals.
        u: (P, S, 2) their fixed light samples (`fixed_light_samples`; the pool's are each caching
            view's own, as the direct Relighter over that view draws them).
        visibility: the shadow queries (`RayVisibility` counts its rays).
        num_groups: G (clamped to [1, S]).
        chunk_samples: points x samples traced together.
    """
    unit = dataclasses.replace(unit_light(light), shaping=None, barzel=None)
    num_samples = u.shape[1]
    groups = sample_groups(num_samples, num_groups).to(position.device)
    num_groups = int(groups.max()) + 1
    step = max(1, chunk_samples // num_samples)
    parts = [
        _chunk_table(
            light,
            unit,
            position[i : i + step],
            normal[i : i + step],
            shading_normal[i : i + step],
            u[i : i + step],
            visibility,
            groups,
            num_groups,
        )
        for i in range(0, position.shape[0], step)
    ]
    if not parts:
        return position.new_zeros(0, num_groups, CHANNELS), position.new_zeros(0)
    return torch.cat([table for table, _ in parts]), torch.cat([unshadowed for _, unshadowed in parts])


def _chunk_table(
    light: Light,
    unit: Light,
    position: torch.Tensor,
    normal: torch.Tensor,
    shading_normal: torch.Tensor,
    u: torch.Tensor,
    visibility,
    groups: torch.Tensor,
    num_groups: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(P, G, 7) and (P,) of the points `position`, `normal`, `shading_normal` (P, 3) with light samples
    u (P, S, 2)."""
    num_samples = u.shape[1]
    sample = sample_light(unit, position, u)
    direction = sample.direction.transpose(0, 1)  # (S, P, 3)
    scalar = sample.inverse_pdf().transpose(0, 1) * (dot(direction, normal) > 0) / num_samples
    weight = sample.radiance.transpose(0, 1) * scalar.unsqueeze(-1)  # (S, P, 3)
    table = position.new_zeros(position.shape[0], num_groups, CHANNELS)
    unshadowed = position.new_zeros(position.shape[0])
    live = (weight != 0).any(-1).any(0)
    index = torch.nonzero(live).squeeze(-1)
    if index.numel() == 0:
        return table, unshadowed
    estimate_weight = estimate_weights(unit, sample.distance, sample.radiance).transpose(0, 1)
    distance = sample.distance.transpose(0, 1)
    if index.numel() < live.shape[0]:  # else every point: no copies

        def pick(values: torch.Tensor) -> torch.Tensor:
            return values.index_select(0, index)

        position, normal, shading_normal = pick(position), pick(normal), pick(shading_normal)
        direction, weight, scalar, estimate_weight, distance = (
            v.index_select(1, index) for v in (direction, weight, scalar, estimate_weight, distance)
        )
    # The samples' unshadowed estimate of the cosine-weighted solid angle, for the ratio estimator.
    cosine = dot(direction, shading_normal)
    ratio = analytic_ratio(unit, position, shading_normal, (scalar * cosine.clamp(min=0.0) * estimate_weight).sum(0))
    distance = visibility.occluder_distance(
        unit, position, normal, direction.transpose(0, 1), distance.transpose(0, 1)
    ).transpose(0, 1)
    if light.shaping is not None or light.barzel is not None:
        local = torch.nn.functional.normalize(LightFrame.of(light, direction).vector_to_local(-direction), dim=-1)
        origin = torch.as_tensor(light.world_from_light[:3, 3], device=position.device, dtype=position.dtype)
        factor = emission_factor(light, local, position, origin)
        assert factor is not None  # the light has shaping or Barzel controls
        weight = weight * factor
    lit = weight.sum((0, 2))
    if unit.shadow.enable:
        weight = weight * shadow_factor(unit.shadow, torch.isfinite(distance), distance)
    values = torch.cat([weight, direction * weight.mean(-1, keepdim=True)], -1)  # (S, P, 6)
    grouped = values.new_zeros(num_groups, values.shape[1], CHANNELS)
    if num_groups == 1:
        grouped[0, :, :6] = values.sum(0)
    else:
        grouped[..., :6].index_add_(0, groups, values)
    grouped[..., 6] = 1.0 if ratio is None else ratio
    if index.numel() < live.shape[0]:
        table.index_copy_(0, index, grouped.transpose(0, 1))
        unshadowed.index_copy_(0, index, lit)
        return table, unshadowed
    return grouped.transpose(0, 1).contiguous(), lit


def view_colours(params: PreviewSurfaceParams) -> torch.Tensor:
    """(F, N, 3) `preview_surface.factor_colours` of a view's N materials (F = 6 with a clearcoat
    anywhere, else 4): what `group_images` weighs the BRDF's factors by, the same for every light."""
    return preview_surface.factor_colours(params, bool(params.clearcoat.any()))


def view_directions(wo: torch.Tensor, normal: torch.Tensor, geometric_normal: torch.Tensor) -> torch.Tensor:
    """(9, N) what `group_images` reads of a view's N points, component rows: the unit world
    directions to the viewer, the unit shading normals and the geometric normals (facing the
    viewer), each (N, 3). The same for every light: made once per view."""
    return torch.cat([wo, normal, geometric_normal], 1).T.contiguous()


def group_images(
    params: PreviewSurfaceParams, directions: torch.Tensor, table: torch.Tensor, colours: torch.Tensor | None = None
) -> torch.Tensor:
    """(2, N, 3) diffuse and specular unit images of N points from their W and D.

    The BRDF is `preview_surface.split` through its factored form (scalars per group and point,
    times the per-material `factor_colours`): equal to it, with the colour work done once per view
    rather than once per light and group. It is isotropic, so the scalars need only N.E, N.L and
    E.L (`preview_surface.split_factors_cosines`, in place): no tangent frame, no local directions.

    Args:
        params: (N,) materials; directions: (9, N) `view_directions` of the points.
        table: (7, G, N) the points' (blended) incident groups, channels first (`CHANNELS`).
        colours: (F, N, 3) `view_colours(params)`, or None to compute them here.
    """
    num_points, rows = directions.shape[1], directions
    cos_e = rows[0] * rows[3] + rows[1] * rows[4] + rows[2] * rows[5]
    # Points the light reaches and whose shading normal faces the viewer (as the Relighter's transport).
    reached = (table[:3].abs().sum(0) > 0).any(0) & (cos_e > 0)
    count = int(reached.sum())
    if count == 0:
        return rows.new_zeros(2, num_points, 3)
    if colours is None:
        colours = view_colours(params)
    coat = colours.shape[0] > 4
    roughnesses = (params.roughness, params.clearcoat_roughness)[: 1 + coat]
    # Most points lit: shade them all (masked) rather than gather the lit ones and scatter back.
    live = None if 2 * count > num_points else torch.nonzero(reached).squeeze(-1)
    if live is not None:
        table, colours, rows = table.index_select(2, live), colours.index_select(1, live), rows.index_select(1, live)
        cos_e, roughnesses = cos_e.index_select(0, live), tuple(r.index_select(0, live) for r in roughnesses)
    # Unit group directions, component by component ((G, P) slabs), against the view's directions.
    dx, dy, dz = table[3], table[4], table[5]
    inverse = torch.rsqrt((dx * dx + dy * dy + dz * dz).clamp_(min=1e-30))

    def along(axis: int) -> torch.Tensor:
        return dx * rows[axis] + dy * rows[axis + 1] + dz * rows[axis + 2]

    e_dot_l, cos_l = along(0).mul_(inverse), along(3).mul_(inverse)
    valid = along(6) > 0  # the light on the geometric side too (N.L: the function's)
    if live is None:
        valid &= reached
    groups, points = cos_l.shape
    factors = cos_l.new_empty(4 + 2 * coat, groups, points)
    # Points first, groups last, as the function lays them out: views of the (G, P) slabs.
    preview_surface.split_factors_cosines(
        tuple(r[:, None] for r in roughnesses),
        cos_e[:, None],
        cos_l.T,
        e_dot_l.T,
        valid.to(cos_l.dtype).T,
        factors.transpose(1, 2),
        cos_l.new_empty(4, points, groups),
    )  # (F, G, P)
    light = table[:3].permute(1, 2, 0)  # (G, P, 3)
    if groups == 1:  # one group: its light factors out of the sum
        diffuse, specular = preview_surface.combine_factors(colours, factors[:, 0, :, None])
        diffuse.mul_(light[0]).mul_(table[6, 0, :, None])
        specular.mul_(light[0])
    else:
        sums = (factors.unsqueeze(-1) * light).sum(1)  # (F, P, 3)
        diffuse, specular = preview_surface.combine_factors(colours, sums)
        diffuse.mul_(table[6, 0, :, None])
    if live is None:
        return torch.stack([diffuse, specular])
    return rows.new_zeros(2, num_points, 3).index_copy_(1, live, torch.stack([diffuse, specular]))
