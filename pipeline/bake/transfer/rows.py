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
"""

from __future__ import annotations

import math

import numpy as np
import torch

from relight_torch.gbuffer import GBuffer
from relight_torch.math.frame import to_local
from relight_torch.shading import reflected_radiance
from relight_torch.indirect_samples import GatherSamples
from relight_torch.visibility.rays import RayCaster


def gather_transport(points: torch.Tensor, normals: torch.Tensor, gathers: GatherSamples,
                     caster: RayCaster) -> tuple[torch.Tensor, torch.Tensor]:
    """Directions to every gather and the clamped, shadowed geometric term.

    Args:
        points: (R, 3) receiver positions.
        normals: (R, 3) unit normals of the receiving side (rays leave on that side only).
        gathers: the G gathers.
        caster: Embree queries over the scene (`offset_origins`, `occluded`, `epsilon`).

    Returns:
        (wi_world (R, G, 3) unit, weight (R, G) = cos(theta_g) A_g / (r^2 + A_g / pi) V, zero where
        the gather faces away, lies behind the receiver or is hidden).
    """
    offset = gathers.position.unsqueeze(0) - points.unsqueeze(1)
    squared = (offset * offset).sum(-1)
    distance = squared.sqrt()
    wi_world = offset / distance.clamp(min=torch.finfo(points.dtype).tiny).unsqueeze(-1)
    cos_gather = -(wi_world * gathers.normal.unsqueeze(0)).sum(-1)
    facing = (wi_world * normals.unsqueeze(1)).sum(-1) > 0
    live = (squared > 0) & (cos_gather > 0) & facing
    weight = torch.where(live, cos_gather * gathers.area / (squared + gathers.area / math.pi), 0.0)
    rows, cols = torch.nonzero(live, as_tuple=True)
    if rows.numel():
        directions = wi_world[rows, cols].numpy().astype(np.float32)
        origins = caster.offset_origins(points[rows].numpy().astype(np.float32),
                                        normals[rows].numpy().astype(np.float32), directions)
        t_far = (distance[rows, cols].numpy() - 2.0 * caster.epsilon).astype(np.float32)
        blocked = caster.occluded(origins, directions, np.maximum(t_far, 0.0))
        weight[rows[torch.from_numpy(blocked)], cols[torch.from_numpy(blocked)]] = 0.0
    return wi_world, weight


def final_gather_rows(view: GBuffer, rows: slice, gathers: GatherSamples, caster: RayCaster) -> torch.Tensor:
    """(R, G, 3) rows of F for the view samples `rows` of a CPU GBuffer."""
    position = view.position[rows]
    wi_world, weight = gather_transport(position, view.geometric_normal[rows], gathers, caster)
    frame = (view.tangent[rows, None], view.bitangent[rows, None], view.normal[rows, None])
    wo_local = to_local(view.wo_world()[rows], *(f[:, 0] for f in frame))
    wi_local = to_local(wi_world, *frame)
    return reflected_radiance(view.params.index(rows).with_sample_axis(), wo_local.unsqueeze(1), wi_local,
                              weight.unsqueeze(-1))


def bounce_rows(rows: slice, gathers: GatherSamples, caster: RayCaster) -> torch.Tensor:
    """(R, G, 3) rows of M for the gathers `rows` as diffuse receivers."""
    normal = gathers.normal[rows]
    wi_world, weight = gather_transport(gathers.position[rows], normal, gathers, caster)
    cos_receiver = (wi_world * normal.unsqueeze(1)).sum(-1).clamp(min=0.0)
    return (gathers.albedo[rows] / math.pi).unsqueeze(1) * (cos_receiver * weight).unsqueeze(-1)
