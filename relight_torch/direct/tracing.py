"""A light's transport at a chunk of shading points: its fixed light samples, their shadow rays and
the BRDF's per-sample factors (`Transport`), and the transports of a light's chunks joined into one."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from relight_torch.brdf import preview_surface
from relight_torch.direct.brdf_samples import weighted_samples
from relight_torch.direct.points import Points, take
from relight_torch.direct.transport import Transport
from relight_torch.lights.emission import light_radiance_scale
from relight_torch.lights.light import Light, LightKind
from relight_torch.lights.ratio import closed_form, estimate_weights, has_closed_form, ratio_of
from relight_torch.lights.shadow import shadow_factor, shadow_strength
from relight_torch.math.frame import dot, to_local
from relight_torch.visibility import Visibility

# The kinds whose emission ShapingAPI and Barzel controls shape (see lights/emission.py).
SHAPED_KINDS = (LightKind.SPHERE, LightKind.RECT, LightKind.DISK, LightKind.CYLINDER)


def scalar_radiance(light: Light) -> bool:
    """Whether the unit light's shadowed radiance L_i V is one colour times a scalar (untextured,
    grey shadow colour): its transport is then kept as scalar factors (`Transport.factors`)."""
    return light.texture is None and bool(light_radiance_scale(light).any()) and len(set(light.shadow.color)) == 1


def filters_visibility(light: Light, filter_radius: int) -> bool:
    """Whether the light's diffuse visibility is filtered (`VisibilityFilter`, radius > 0): lights
    with a closed form, but not domes, whose visibility spans the hemisphere: the filter's one
    sample a point would blur their contact shadows."""
    return filter_radius > 0 and light.kind is not LightKind.DOME and has_closed_form(light)


def chunks(
    num_points: int, chunk_samples: int, num_samples: int, points: torch.Tensor | None, pieces: int = 1
) -> list[slice | torch.Tensor]:
    """Consecutive chunks of all `num_points` shading points (slices) or of `points` (index
    tensors), at least `pieces` of them (where there are enough points), of at most
    `chunk_samples` light samples (`num_samples` a point)."""
    n = num_points if points is None else points.shape[0]
    step = max(1, min(chunk_samples // num_samples, -(-n // pieces)))
    if points is not None:
        return [points[i : i + step] for i in range(0, n, step)] or [points]
    # No covered point (a camera that sees only sky) is one empty chunk: an empty transport.
    return [slice(i, min(i + step, n)) for i in range(0, n, step)] or [slice(0, 0)]


def chunk_transport(
    light: Light,
    chunk: slice | torch.Tensor,
    points: Points,
    visibility: Visibility,
    filter_radius: int,
    coat: bool,
) -> Transport:
    """The transport of an unshaped unit light at the shading points of `chunk` (a slice of
    all of them, or their indices), evaluated at `points`: at each shading point, or once per
    pixel group at its centroid (`points.groups`, `direct.sharing`) and taken by each of the
    group's points (the materials' colours enter per point later, `LightStages.per_point`).
    The other arguments as `point_transport`'s."""
    groups = points.groups
    if groups is None:
        return point_transport(light, chunk, points, visibility, filter_radius, coat)
    rows, which = groups.of(chunk)
    transport = point_transport(light, rows, points, visibility, filter_radius, coat)
    whole = None if isinstance(chunk, slice) else chunk
    if transport.points is None or (not isinstance(rows, slice) and transport.points.shape == rows.shape):
        return transport.gathered(which, whole)  # every group kept, in order
    where, held = transport.locate(take(groups.rank, chunk))
    if bool(held.all()):
        return transport.gathered(where, whole)
    indices = torch.arange(chunk.start, chunk.stop, device=which.device) if isinstance(chunk, slice) else chunk
    return transport.gathered(where[held], indices[held])


def point_transport(
    light: Light,
    chunk: slice | torch.Tensor,
    at: Points,
    visibility: Visibility,
    filter_radius: int,
    coat: bool,
) -> Transport:
    """The transport of an unshaped unit light evaluated at each of the points `at` in `chunk`
    (a slice of them, or their indices).

    Points that no sample can light (facing away, inside the light, outside its cone of
    directions) cast no shadow rays and are dropped, unless they are fewer than half the
    chunk: then the whole chunk is kept, its rows read as views rather than gathered.
    Everything runs samples first, (S, P, ...): per-point values broadcast over whole slabs.

    Args:
        visibility: the shadow queries.
        filter_radius: the visibility filter's radius (0: none): with one, a light with a closed
            form keeps its per-point shadow sums (`Transport.shadow_sums`).
        coat: whether the BRDF factors carry the clearcoat lobe (one answer for every chunk).
    """
    g, u, (wo, cos_e, inverse_norm) = at.gbuffer, at.samples, at.viewer
    sample = weighted_samples(light, g, chunk, take(u, chunk), take(wo, chunk))
    direction = sample.direction  # (S, C, 3)
    cosine = dot(direction, take(g.normal, chunk))  # N.L at the shading normal as stored: the closed form's
    facing = dot(direction, take(g.geometric_normal, chunk)) > 0
    # Every per-sample scalar of each lobe in one (S, C) factor: the samples' weight, both
    # hemispheres, cos (`brdf_samples`; one tensor for both lobes without BRDF samples).
    front = ((cosine > 0) & facing) * cosine
    scalar = sample.diffuse_weight * front
    joint = sample.specular_weight is sample.diffuse_weight
    specular_scalar = scalar if joint else sample.specular_weight * front
    radiance = sample.radiance
    lit = ((specular_scalar != 0) & (radiance != 0).any(-1)).any(0)
    exact = closed_form(light, take(g.position, chunk), take(g.normal, chunk))
    filtered = filters_visibility(light, filter_radius)
    if filtered:  # lit by the closed form even where no sample is (see `uncovered` below)
        assert exact is not None  # filtered implies a closed form
        lit |= exact > 0
    lit &= take(cos_e, chunk) > 0
    local: slice | torch.Tensor
    rows: slice | torch.Tensor
    points: torch.Tensor | None
    if 2 * int(lit.sum()) > lit.shape[0]:
        local, rows, points = slice(None), chunk, None if isinstance(chunk, slice) else chunk
    else:
        local = torch.nonzero(lit).squeeze(-1)
        rows = points = local + chunk.start if isinstance(chunk, slice) else chunk[local]
    direction, cosine = direction[:, local], cosine[:, local]
    scalar, radiance = scalar[:, local], radiance[:, local]
    specular_scalar = scalar if joint else specular_scalar[:, local]
    light_distance = sample.distance[:, local]
    distance = visibility.occluder_distance(
        light,
        take(g.position, rows),
        take(g.geometric_normal, rows),
        direction.transpose(0, 1),
        light_distance.transpose(0, 1),
    )
    distance = distance.transpose(0, 1)
    ratio = None
    if exact is not None:  # against the samples' unshadowed estimate of the cosine-weighted solid angle
        estimate = (scalar * estimate_weights(light, light_distance, radiance)).sum(0)
        ratio = ratio_of(take(exact, local), estimate)
    params, wo, shadow = g.params.index(rows), take(wo, rows), light.shadow
    scale = light_radiance_scale(light)
    if scalar_radiance(light):
        # L_i V = colour x scalar: keep per-sample scalars, not (S, P, 3) colours.
        k = int(np.argmax(np.abs(scale)))
        emitted = radiance[..., k] / float(scale[k])
        unshadowed = scalar * emitted
        weight, specular_weight = unshadowed, unshadowed if joint else specular_scalar * emitted
        if shadow.enable:
            shadowing = 1.0 - (1.0 - shadow.color[0]) * shadow_strength(shadow, distance < math.inf, distance)
            weight = unshadowed * shadowing
            specular_weight = weight if joint else specular_weight * shadowing
        factors = preview_surface.split_factors(
            params, take(cos_e, rows), cosine * take(inverse_norm, rows), dot(direction, wo), coat
        )
        # With a filtered visibility the diffuse factors stay unshadowed (see Transport).
        factors[:2] *= unshadowed if filtered else weight
        factors[2:] *= specular_weight
        sums = None
        if filtered:
            assert exact is not None  # filtered implies a closed form
            sums = torch.stack((weight.sum(0), unshadowed.sum(0)), dim=-1)
            # Points whose samples all fall below their horizon (a tangent plane cutting the
            # light) take the closed form as their unshadowed diffuse sum (Fresnel's s taken
            # as 0) and their visibility from the filter's neighbours.
            uncovered = torch.nonzero((sums[:, 1] == 0) & (take(exact, local) > 0)).squeeze(-1)
            factors[0, 0, uncovered] = take(exact, local)[uncovered]
        colour = torch.as_tensor(scale, device=factors.device, dtype=factors.dtype)
        if light.kind not in SHAPED_KINDS:
            return Transport(points, None, None, ratio, factors.sum(1, keepdim=True), colour, sums)
        return Transport(points, direction, None, ratio, factors, colour, sums)
    weight = radiance * scalar.unsqueeze(-1)
    specular_weight = weight if joint else radiance * specular_scalar.unsqueeze(-1)
    if shadow.enable:
        shadowing = shadow_factor(shadow, distance < math.inf, distance)
        weight = weight * shadowing
        specular_weight = weight if joint else specular_weight * shadowing
    frame = (take(g.tangent, rows), take(g.bitangent, rows), take(g.normal, rows))
    diffuse, specular = preview_surface.split(params, to_local(wo, *frame), to_local(direction, *frame))
    lobes = weight.new_empty(2, *weight.shape)
    torch.mul(diffuse, weight, out=lobes[0])
    torch.mul(specular, specular_weight, out=lobes[1])
    if light.kind not in SHAPED_KINDS:
        return Transport(points, None, lobes.sum(1, keepdim=True), ratio)
    return Transport(points, direction, lobes, ratio)


def joined(
    parts: list[Transport], chunks: list[slice | torch.Tensor], num_points: int, device: torch.device
) -> Transport:
    """One transport from the transports of consecutive chunks of the `num_points` shading points
    (on `device`).

    Sparse parts keep their point lists; when the points reached are over half of all, every
    tensor is scattered to all N points (zeros elsewhere, ratio 1) and the list dropped.
    """
    n = num_points

    def reached(chunk: slice | torch.Tensor, part: Transport) -> torch.Tensor:
        if part.points is not None:
            return part.points
        assert isinstance(chunk, slice), "only a transport of a slice of all points drops its point list"
        return torch.arange(chunk.start, chunk.stop, device=device)

    points = None
    if any(part.points is not None for part in parts):
        points = torch.cat([reached(chunk, part) for chunk, part in zip(chunks, parts, strict=True)])
    dense_points = points if points is not None and 2 * points.shape[0] > n else None
    dense = dense_points is not None

    def join(name: str, dim: int, fill: float) -> torch.Tensor | None:
        values = [getattr(part, name) for part in parts]
        if values[0] is None:
            return None
        joined = torch.cat(values, dim=dim)
        if dense_points is not None:
            shape = list(joined.shape)
            shape[dim] = n
            joined = joined.new_full(shape, fill).index_copy_(dim, dense_points, joined)
        return joined

    return Transport(
        None if dense else points,
        join("directions", 1, 0.0),
        join("lobes", 2, 0.0),
        join("diffuse_ratio", 0, 1.0),
        join("factors", 2, 0.0),
        parts[0].colour,
        join("shadow_sums", 0, 0.0),
    )


def _reorder(values: torch.Tensor | None, order: torch.Tensor) -> torch.Tensor | None:
    return None if values is None else values.index_select(0, order)


def kept_transport(group: list[tuple[torch.Tensor, Transport]], num_points: int, device: torch.device) -> Transport:
    """One sample group's transport from the parts traced for its points, point by point
    (`Progress.parts`): joined as `joined` joins a light's tiles, its points ascending."""
    chunks: list[slice | torch.Tensor] = [chunk for chunk, _ in group]
    transport = joined([part for _, part in group], chunks, num_points, device)
    if transport.points is None:
        return transport
    order = torch.argsort(transport.points)
    subset = dataclasses.replace(transport, points=None).subset(order)
    return dataclasses.replace(
        subset, points=transport.points[order], shadow_sums=_reorder(transport.shadow_sums, order)
    )
