"""Where a light's emitting surface is: its frame, world-space size, area samples and ray hits.

The light frame is `Light.world_from_light` (column vectors). Rect and disk lie in the local XY
plane (centred, emitting towards -Z); the cylinder's axis is local X; the sphere is centred at the
origin. An affine map keeps the ray parameter, so rays are intersected in the light's local frame
and the hit distance is already the world distance along a unit world direction.

Transforms the exact samplers need (checked by `check_transform`): the sphere and the dome need a
similarity (rotation times one scale); the cylinder needs local Y and Z scaled equally and all
three axes kept orthogonal (X may be stretched). Rect and disk accept any invertible affine map.
Positions, axis scales and world-space sizes are bounded by `MAX_EXTENT` (`check_extent`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from relight_torch.lights.light import Light, LightKind
from relight_torch.math.frame import length

_ORTHOGONALITY_TOLERANCE = 1e-4

MAX_EXTENT = 1e15
"""Largest world-space coordinate, axis scale or size of a light (scene units). The kernels square
distances and multiply sizes in float32 (largest value 3.4e38): squares of 1e15 (1e30) leave room
for the products that follow, while squares of 1e19 and more overflow to inf and end in non-finite
pixels. Anything farther than this is better described by a distant or dome light."""


@dataclass(frozen=True)
class LightFrame:
    """A light's transform as tensors of one device and dtype.

    Attributes:
        origin: (3,) light origin in world space.
        world_from_light: (3, 3) linear part (column vectors).
        light_from_world: (3, 3) its inverse.
        normal_to_world: (3, 3) inverse transpose, for local normals.
    """

    origin: torch.Tensor
    world_from_light: torch.Tensor
    light_from_world: torch.Tensor
    normal_to_world: torch.Tensor

    @staticmethod
    def of(light: Light, like: torch.Tensor) -> LightFrame:
        """The frame of `light` on the device and in the dtype of `like`."""
        linear = light.world_from_light[:3, :3]
        inverse = np.linalg.inv(linear)

        def tensor(array: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(array, device=like.device, dtype=like.dtype)

        return LightFrame(tensor(light.world_from_light[:3, 3]), tensor(linear), tensor(inverse), tensor(inverse.T))

    def point_to_local(self, points: torch.Tensor) -> torch.Tensor:
        """World points (..., 3) to light-local points (..., 3)."""
        return transform_rows(points - self.origin, self.light_from_world)

    def vector_to_local(self, vectors: torch.Tensor) -> torch.Tensor:
        """World vectors (..., 3) to light-local vectors (..., 3), not renormalised."""
        return transform_rows(vectors, self.light_from_world)

    def point_to_world(self, points_local: torch.Tensor) -> torch.Tensor:
        """Light-local points (..., 3) to world points (..., 3)."""
        return transform_rows(points_local, self.world_from_light).add_(self.origin)

    def vector_to_world(self, vectors_local: torch.Tensor) -> torch.Tensor:
        """Light-local vectors (..., 3) to world vectors (..., 3), not renormalised."""
        return transform_rows(vectors_local, self.world_from_light)

    def normal_to_world_unit(self, normals_local: torch.Tensor) -> torch.Tensor:
        """Light-local normals (..., 3) to unit world normals (..., 3) (inverse transpose)."""
        return torch.nn.functional.normalize(transform_rows(normals_local, self.normal_to_world), dim=-1)


def transform_rows(vectors: torch.Tensor, matrix: torch.Tensor) -> torch.Tensor:
    """matrix (3, 3) applied to row vectors (..., 3): vectors @ matrix^T, as a new tensor.

    Through a contiguous copy of the transpose: torch's CPU matmul with a transposed (3, 3) view
    takes a path 2-3x slower (300,000 rows on one thread: 5.5-7.5 ms against 2.3 ms).
    """
    return vectors @ matrix.T.contiguous()


def check_transform(light: Light) -> None:
    """Raise ValueError (naming the light) when its transform defeats its exact sampler."""
    columns = light.world_from_light[:3, :3]
    gram = columns.T @ columns
    scale = np.sqrt(np.diag(gram))
    cosines = gram / np.outer(scale, scale)
    orthogonal = np.abs(cosines - np.eye(3)).max() <= _ORTHOGONALITY_TOLERANCE
    uniform = orthogonal and np.ptp(scale) <= _ORTHOGONALITY_TOLERANCE * scale.max()
    if light.kind in (LightKind.SPHERE, LightKind.DOME) and not uniform:
        raise ValueError(
            f"{light.path}: {light.kind.value} needs a rotation and one uniform scale; "
            f"its transform scales the axes by {np.round(scale, 6).tolist()} or shears"
        )
    circular = orthogonal and abs(scale[1] - scale[2]) <= _ORTHOGONALITY_TOLERANCE * scale.max()
    if light.kind is LightKind.CYLINDER and not circular:
        raise ValueError(
            f"{light.path}: CylinderLight needs orthogonal axes with Y and Z scaled equally "
            f"(a circular cross-section); its axes scale by {np.round(scale, 6).tolist()}"
        )


def check_extent(light: Light) -> None:
    """Raise ValueError (naming the light and attribute) for a position, scale or size beyond `MAX_EXTENT`.

    Run before anything squares the light's sizes (`surface_area`): a radius of 1e300 passes a
    finiteness check but overflows once squared.
    """
    origin = light.world_from_light[:3, 3]
    if not np.abs(origin).max() <= MAX_EXTENT:
        raise ValueError(
            f"{light.path}: xformOp (world transform) puts the light at {_triple(origin)}, "
            f"beyond {MAX_EXTENT:g} scene units from the origin"
        )
    scales = axis_scales(light)
    if not scales.max() <= MAX_EXTENT:
        raise ValueError(
            f"{light.path}: xformOp (world transform) scales the light's axes by {_triple(scales)}, "
            f"beyond {MAX_EXTENT:g}"
        )
    for attribute, size in _world_sizes(light, scales):
        if not size <= MAX_EXTENT:
            raise ValueError(
                f"{light.path}: {attribute} gives a world-space size of {size:g}, beyond {MAX_EXTENT:g} scene units"
            )


def _triple(values: np.ndarray) -> str:
    """'(1e+30, 0, 0)': a short text of three numbers for a message."""
    return "(" + ", ".join(f"{float(value):.6g}" for value in values) + ")"


def _world_sizes(light: Light, scales: np.ndarray) -> list[tuple[str, float]]:
    """(attribute, world-space size) of each size input the light's kind uses (plain floats, inf on overflow)."""
    x, y = float(scales[0]), float(scales[1])
    if light.kind is LightKind.SPHERE:
        return [("inputs:radius", light.radius * y)]
    if light.kind is LightKind.RECT:
        return [("inputs:width", light.width * x), ("inputs:height", light.height * y)]
    if light.kind is LightKind.DISK:
        return [("inputs:radius", light.radius * max(x, y))]
    if light.kind is LightKind.CYLINDER:
        return [("inputs:length", light.length * x), ("inputs:radius", light.radius * y)]
    return []


def axis_scales(light: Light) -> np.ndarray:
    """(3,) world length of the light's unit local X, Y and Z axes."""
    scales: np.ndarray = np.linalg.norm(light.world_from_light[:3, :3], axis=0)
    return scales


def world_radius(light: Light) -> float:
    """World radius of a sphere (uniform scale) or cylinder (Y scale) light."""
    return light.radius * float(axis_scales(light)[1])


def surface_area(light: Light) -> float:
    """World-space emitting area of an area light, transform scale included (no cylinder caps)."""
    columns = light.world_from_light[:3, :3]
    plane_scale = float(np.linalg.norm(np.cross(columns[:, 0], columns[:, 1])))
    if light.kind is LightKind.SPHERE:
        return 4.0 * math.pi * world_radius(light) ** 2
    if light.kind is LightKind.RECT:
        return light.width * light.height * plane_scale
    if light.kind is LightKind.DISK:
        return math.pi * light.radius**2 * plane_scale
    if light.kind is LightKind.CYLINDER:
        return 2.0 * math.pi * world_radius(light) * light.length * float(axis_scales(light)[0])
    raise ValueError(f"{light.path}: {light.kind.value} has no emitting surface")


def sample_area_local(light: Light, disk_points: torch.Tensor | None, u: torch.Tensor) -> torch.Tensor:
    """Uniform-area points on a rect, disk or cylinder light, in its local frame.

    Uniform in local area is uniform in world area under the transforms `check_transform` allows.

    Args:
        light: a RECT, DISK or CYLINDER light.
        disk_points: (..., 2) points of the unit disk, uniform in area (used by the disk only:
            None for the others).
        u: (..., 2) uniform numbers in [0, 1).

    Returns:
        (..., 3) local points on the emitting surface.
    """
    zero = torch.zeros_like(u[..., 0])
    if light.kind is LightKind.RECT:
        return torch.stack(((u[..., 0] - 0.5) * light.width, (u[..., 1] - 0.5) * light.height, zero), dim=-1)
    if light.kind is LightKind.DISK:
        assert disk_points is not None, "a disk light's points need disk_points"
        return torch.cat((disk_points * light.radius, zero.unsqueeze(-1)), dim=-1)
    phi = 2.0 * math.pi * u[..., 1]
    return torch.stack(
        ((u[..., 0] - 0.5) * light.length, light.radius * torch.cos(phi), light.radius * torch.sin(phi)), dim=-1
    )


@dataclass(frozen=True)
class SurfaceHits:
    """Where rays meet an area light's surface (the first hit), and the area-sampling density.

    Attributes:
        distance: (...) world distance to the first hit; inf on a miss.
        point_local: (..., 3) first hit in the light's frame (meaningless on a miss).
        cos_light: (...) cosine between the surface's emitting normal and the direction back to the
            ray origin at the first hit (> 0: the emitting side faces the origin).
        pdf: (...) solid-angle density with which uniform area sampling produces the direction:
            the sum of d^2 / (A |cos|) over every crossing of the surface (a cylinder is crossed
            twice); 0 on a miss.
    """

    distance: torch.Tensor
    point_local: torch.Tensor
    cos_light: torch.Tensor
    pdf: torch.Tensor


def intersect_surface(light: Light, frame: LightFrame, origins: torch.Tensor, directions: torch.Tensor) -> SurfaceHits:
    """Intersect rays with a rect, disk or cylinder light.

    Args:
        light: a RECT, DISK or CYLINDER light.
        frame: its frame on the rays' device/dtype.
        origins: (..., 3) world ray origins; directions: (..., 3) unit world directions (broadcast).

    Returns:
        SurfaceHits with the broadcast shape of the rays.
    """
    # Per-origin work on the unbroadcast origins (samples share their receiver), then broadcast.
    origin_local = frame.point_to_local(origins)
    origins, directions = torch.broadcast_tensors(  # type: ignore[no-untyped-call]  # unannotated in torch
        origins, directions
    )
    origin_local = origin_local.expand(origins.shape)
    direction_local = frame.vector_to_local(directions)
    area = surface_area(light)
    if light.kind is LightKind.CYLINDER:
        crossings = _cylinder_crossings(light, origin_local, direction_local)
    else:
        crossings = [_plane_crossing(light, origin_local, direction_local)]
    first = torch.full_like(origins[..., 0], math.inf)
    pdf = torch.zeros_like(first)
    first_cos = torch.zeros_like(first)
    for distance, normal_local in crossings:
        cos_light = -(frame.normal_to_world_unit(normal_local) * directions).sum(-1)
        pdf = pdf + _solid_angle_density(distance, cos_light, torch.isfinite(distance), area)
        nearer = distance < first
        first_cos = torch.where(nearer, cos_light, first_cos)
        first = torch.where(nearer, distance, first)
    point_local = origin_local + torch.where(torch.isfinite(first), first, 0.0).unsqueeze(-1) * direction_local
    return SurfaceHits(first, point_local, first_cos, pdf)


def planar_hits(
    light: Light, frame: LightFrame, origins: torch.Tensor, point_local: torch.Tensor
) -> tuple[torch.Tensor, SurfaceHits]:
    """Rays from `origins` (..., 3) aimed at local points (..., 3) of a rect or disk light.

    A ray meets a plane once, at the point it was aimed at, so the hits need no intersection:
    they equal `intersect_surface` along the returned directions up to rounding.

    Returns:
        (unit world directions (..., 3), SurfaceHits of the broadcast shape).
    """
    to_light = frame.point_to_world(point_local) - origins
    distance = length(to_light)
    directions = to_light / distance.clamp_min(torch.finfo(distance.dtype).tiny).unsqueeze(-1)
    emitting = frame.normal_to_world_unit(to_light.new_tensor([0.0, 0.0, -1.0]))
    cos_light = -(directions @ emitting)
    hit = (cos_light != 0) & (distance > 0)
    return directions, SurfaceHits(
        torch.where(hit, distance, math.inf),
        point_local,
        cos_light,
        _solid_angle_density(distance, cos_light, hit, surface_area(light)),
    )


def _solid_angle_density(
    distance: torch.Tensor, cos_light: torch.Tensor, hit: torch.Tensor, area: float
) -> torch.Tensor:
    """d^2 / (A |cos|) where `hit`, else 0: uniform area sampling's density in solid angle."""
    safe_cos = torch.where(hit, cos_light.abs(), torch.ones_like(cos_light))
    return torch.where(hit, distance.square() / (area * safe_cos), torch.zeros_like(distance))


def _plane_crossing(
    light: Light, origin_local: torch.Tensor, direction_local: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(distance (...) inf on a miss, emitting normal (..., 3) = local -Z) for a rect or disk."""
    distance = -origin_local[..., 2] / direction_local[..., 2]
    point = origin_local + torch.nan_to_num(distance, posinf=0.0, neginf=0.0).unsqueeze(-1) * direction_local
    if light.kind is LightKind.RECT:
        inside = (point[..., 0].abs() <= 0.5 * light.width) & (point[..., 1].abs() <= 0.5 * light.height)
    else:
        inside = point[..., 0].square() + point[..., 1].square() <= light.radius**2
    hit = inside & (distance > 0) & torch.isfinite(distance)
    normal = torch.tensor([0.0, 0.0, -1.0], device=point.device, dtype=point.dtype)  # broadcasts
    return torch.where(hit, distance, math.inf), normal


def _cylinder_crossings(
    light: Light, origin_local: torch.Tensor, direction_local: torch.Tensor
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Both crossings of the cylinder's side: [(distance inf if none, outward normal (..., 3))] * 2."""
    oy, oz = origin_local[..., 1], origin_local[..., 2]
    dy, dz = direction_local[..., 1], direction_local[..., 2]
    a = dy.square() + dz.square()
    half_b = oy * dy + oz * dz
    c = oy.square() + oz.square() - light.radius**2
    discriminant = half_b.square() - a * c
    root = torch.sqrt(discriminant.clamp_min(0.0))
    # Numerically stable pair of roots: q = -(b/2 + sign(b/2) sqrt), t0 = q / a, t1 = c / q.
    q = -(half_b + torch.copysign(root, half_b))
    crossings = []
    for distance in (q / a, c / q):
        point = origin_local + torch.nan_to_num(distance, posinf=0.0, neginf=0.0).unsqueeze(-1) * direction_local
        hit = (
            (discriminant >= 0)
            & (a > 0)
            & (distance > 0)
            & torch.isfinite(distance)
            & (point[..., 0].abs() <= 0.5 * light.length)
        )
        normal = torch.stack((torch.zeros_like(oy), point[..., 1], point[..., 2]), dim=-1)
        crossings.append((torch.where(hit, distance, math.inf), normal))
    return crossings
