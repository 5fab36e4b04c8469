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
`group_images` shades a new view's points from their blended W, D: the direct BRDF
(`preview_surface.split`, the only BRDF) at the point's own wo and frame, evaluated once per group
at wi_g = D_g / |D_g|:

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
from relight_torch.light_samples import fixed_light_samples
from relight_torch.lights.emission import sample_light
from relight_torch.lights.geometry import LightFrame
from relight_torch.lights.light import Light
from relight_torch.lights.polygon import analytic_ratio
from relight_torch.lights.shadow import shadow_factor
from relight_torch.lights.shaping import emission_factor
from relight_torch.math.frame import dot
from relight_torch.relighter import unit_light

CHANNELS = 7
"""Columns per group in a table: W (RGB), D (xyz), then the light's ratio-estimator factor on the
diffuse sum (`lights.polygon.analytic_ratio`, as the direct Relighter applies it; 1 for lights
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


def pool_light_samples(counts: list[int], num_samples: int, seed: int, device: torch.device,
                       dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(R, S, 2) fixed light samples of a pool of views with `counts` samples each: each view's
    own `fixed_light_samples(N_k, S, seed)`, those the direct Relighter over that view draws."""
    parts = [fixed_light_samples(n, num_samples, seed, device, dtype) for n in counts if n]
    return torch.cat(parts) if parts else torch.zeros((0, num_samples, 2), device=device, dtype=dtype)


def incident_table(light: Light, position: torch.Tensor, normal: torch.Tensor, shading_normal: torch.Tensor,
                   u: torch.Tensor, visibility, num_groups: int, chunk_samples: int = 1 << 20) -> torch.Tensor:
    """(P, G, 7) float32 W, D and the diffuse ratio (module docstring) of `light` at P points.

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
    parts = [_chunk_table(light, unit, position[i:i + step], normal[i:i + step], shading_normal[i:i + step],
                          u[i:i + step], visibility, groups, num_groups) for i in range(0, position.shape[0], step)]
    return torch.cat(parts) if parts else position.new_zeros(0, num_groups, CHANNELS)


def _chunk_table(light: Light, unit: Light, position: torch.Tensor, normal: torch.Tensor,
                 shading_normal: torch.Tensor, u: torch.Tensor, visibility, groups: torch.Tensor,
                 num_groups: int) -> torch.Tensor:
    """(P, G, 7) of the points `position`, `normal`, `shading_normal` (P, 3) with light samples u (P, S, 2)."""
    num_samples = u.shape[1]
    sample = sample_light(unit, position, u)
    direction = sample.direction.transpose(0, 1)                                  # (S, P, 3)
    scalar = sample.inverse_pdf().transpose(0, 1) * (dot(direction, normal) > 0) / num_samples
    weight = sample.radiance.transpose(0, 1) * scalar.unsqueeze(-1)               # (S, P, 3)
    live = (weight != 0).any(-1).any(0)
    index = torch.nonzero(live).squeeze(-1)
    table = position.new_zeros(position.shape[0], num_groups, CHANNELS)
    if index.numel() == 0:
        return table
    # The samples' unshadowed estimate of the cosine-weighted solid angle, for the ratio estimator.
    cosine = dot(direction[:, index], shading_normal[index])
    reaching = torch.isfinite(sample.distance).transpose(0, 1)[:, index]
    ratio = analytic_ratio(unit, position[index], shading_normal[index],
                           (scalar[:, index] * cosine.clamp(min=0.0) * reaching).sum(0))
    direction, weight = direction[:, index], weight[:, index]
    distance = visibility.occluder_distance(unit, position[index], normal[index], direction.transpose(0, 1),
                                            sample.distance.transpose(0, 1)[:, index].transpose(0, 1))
    distance = distance.transpose(0, 1)
    if unit.shadow.enable:
        weight = weight * shadow_factor(unit.shadow, torch.isfinite(distance), distance)
    if light.shaping is not None or light.barzel is not None:
        local = torch.nn.functional.normalize(LightFrame.of(light, direction).vector_to_local(-direction), dim=-1)
        origin = torch.as_tensor(light.world_from_light[:3, 3], device=position.device, dtype=position.dtype)
        weight = weight * emission_factor(light, local, position[index], origin)
    values = torch.cat([weight, direction * weight.mean(-1, keepdim=True)], -1)  # (S, P, 6)
    grouped = values.new_zeros(num_groups, index.shape[0], CHANNELS)
    grouped[..., :6].index_add_(0, groups, values)
    grouped[..., 6] = 1.0 if ratio is None else ratio
    table[index] = grouped.transpose(0, 1)
    return table


def view_colours(params: PreviewSurfaceParams) -> torch.Tensor:
    """(F, N, 3) `preview_surface.factor_colours` of a view's N materials (F = 6 with a clearcoat
    anywhere, else 4): what `group_images` weighs the BRDF's factors by, the same for every light."""
    return preview_surface.factor_colours(params, bool(params.clearcoat.any()))


def group_images(params: PreviewSurfaceParams, wo_local: torch.Tensor, tangent: torch.Tensor,
                 bitangent: torch.Tensor, normal: torch.Tensor, geometric_normal: torch.Tensor,
                 table: torch.Tensor, colours: torch.Tensor | None = None) -> torch.Tensor:
    """(2, N, 3) diffuse and specular unit images of N points from their W and D.

    The BRDF is `preview_surface.split` through its factored form (`split_factors`, scalars per
    group and point, times the per-material `factor_colours`): equal to it, with the colour
    work done once per view rather than once per light and group.

    Args:
        params: (N,) materials; wo_local: (N, 3) unit direction to the viewer in the shading frame
            (tangent, bitangent, normal), each (N, 3); geometric_normal: (N, 3), facing the viewer.
        table: (7, G, N) the points' (blended) incident groups, channels first (`CHANNELS`).
        colours: (F, N, 3) `view_colours(params)`, or None to compute them here.
    """
    num_points = wo_local.shape[0]
    # Points the light reaches and whose shading normal faces the viewer (as the Relighter's transport).
    reached = (table[:3].abs().sum(0) > 0).any(0) & (wo_local[:, 2] > 0)
    count = int(reached.sum())
    if count == 0:
        return wo_local.new_zeros(2, num_points, 3)
    if colours is None:
        colours = view_colours(params)
    # Most points lit: shade them all (masked) rather than gather the lit ones and scatter back.
    live = None if 2 * count > num_points else torch.nonzero(reached).squeeze(-1)

    def pick(values: torch.Tensor) -> torch.Tensor:
        return values if live is None else values.index_select(0, live)

    if live is not None:
        table = table.index_select(2, live)
        colours = colours.index_select(1, live)
    # Unit group directions and their local frame, component by component ((G, P) slabs).
    dx, dy, dz = table[3], table[4], table[5]
    inverse = torch.rsqrt((dx * dx + dy * dy + dz * dz).clamp_(min=1e-30))
    dx, dy, dz = dx * inverse, dy * inverse, dz * inverse
    tangent, bitangent, normal, geometric_normal = (pick(v) for v in (tangent, bitangent, normal, geometric_normal))
    wi_local = torch.stack([dx * frame[:, 0] + dy * frame[:, 1] + dz * frame[:, 2]
                            for frame in (tangent, bitangent, normal)], -1)                  # (G, P, 3)
    cosine = wi_local[..., 2]
    facing = dx * geometric_normal[:, 0] + dy * geometric_normal[:, 1] + dz * geometric_normal[:, 2] > 0
    valid = (cosine > 0) & facing
    if live is None:
        valid &= reached
    material = dataclasses.replace(params, **{f.name: pick(getattr(params, f.name))
                                              for f in dataclasses.fields(params)})
    factors = preview_surface.split_factors(material, pick(wo_local), wi_local, colours.shape[0] > 4,
                                            weight=cosine * valid)                           # (F, G, P)
    light = table[:3].permute(1, 2, 0)                                                      # (G, P, 3)
    if light.shape[0] == 1:  # one group: its light factors out of the sum
        diffuse, specular = preview_surface.combine_factors(colours, factors[:, 0, :, None])
        diffuse.mul_(light[0]).mul_(table[6, 0, :, None])
        specular.mul_(light[0])
    else:
        sums = (factors.unsqueeze(-1) * light).sum(1)                                       # (F, P, 3)
        diffuse, specular = preview_surface.combine_factors(colours, sums)
        diffuse.mul_(table[6, 0, :, None])
    if live is None:
        return torch.stack([diffuse, specular])
    return wo_local.new_zeros(2, num_points, 3).index_copy_(1, live, torch.stack([diffuse, specular]))
