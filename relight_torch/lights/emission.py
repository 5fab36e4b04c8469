"""What a `Light` emits: the project's radiometry, written once (USD_EXR_NOTES 1.2-1.4; hdEmbree).

Radiance leaving a point of the light towards a receiver, in nits (linear Rec.709 RGB):

    L = intensity * 2^exposure * color
        * BlackbodyTemperatureAsRgb(colorTemperature)     if enableColorTemperature
        / sizeFactor                                      if normalize
        * texture                                         rect: bilinear; dome: lat-long, nearest
        * shaping(e) * barzel(e, distance)                area lights (sphere, rect, disk, cylinder)
        * [the emitting side faces the receiver]

The first three lines are `light_radiance_scale`. `pxr.UsdLux.BlackbodyTemperatureAsRgb` is the one
colour-temperature function; we do NOT renormalise it to white (6500 K gives (1.043, 0.984, 1.035),
luminance 1), exactly as the schema function returns it. `diffuse` and `specular` are per-lobe
multipliers that the shading code applies; they are not part of L. Camera exposure is not applied
here.

sizeFactor: the light's world-space emitting area, transform scale included, for sphere (4 pi r^2),
rect (w h), disk (pi r^2) and cylinder (2 pi r l, no caps); for the distant light, with
thetaMax = clamp(radians(angle) / 2, 0, pi): 1 if thetaMax = 0, pi sin^2(thetaMax) up to pi/2,
pi (2 - sin^2(thetaMax)) above; 1 for the dome. So a normalized area light emits a total power of
pi * intensity * 2^exposure whatever its size, and a normalized distant light's intensity is the
illuminance (lux) on a surface facing it. Without normalize, the 26.11 fallback distant light
(intensity 50000, angle 0.53) gives E = 50000 pi sin^2(0.265 deg) = 3.36 lux, not 50000.

Per type (local frame: `Light.world_from_light`; e = emission direction in it, from the emitting
point towards the receiver; the light's axis is -Z):
    * Sphere: emits outward, one-sided, nothing reaches a receiver inside it. `treatAsPoint` is a
      hint we ignore, as hdEmbree does: the sphere keeps its radius. A radius-0 sphere is a point
      light (delta): it emits nothing unless normalize is on, when its radiant intensity is
      I = intensity * 2^exposure * color [* blackbody] / 4 (the r -> 0 limit of a normalized
      sphere: pi r^2 L with L = intensity / (4 pi r^2)), shaped like an area light.
    * Rect, Disk: one side, towards local -Z. Rect texture: image pixel (0, 0) (top-left) at local
      (+X, +Y) and the image's far corner at (-X, -Y), so the receiver sees it unmirrored.
    * Cylinder: emits outward from its side (axis local X), no caps. `treatAsLine` is ignored.
    * Distant: uniform radiance over the cone of half-angle thetaMax around the direction to the
      light (local +Z); angle 0 is a delta light whose irradiance on a surface facing it is L.
      Shaping and Barzel controls do not apply.
    * Dome: radiance arriving from direction d is the lat-long image at d (see `dome`), or L
      everywhere without a texture. Shaping and Barzel controls do not apply.
    * ShapingAPI (`shaping`), RelightBarzelLightAPI (`shaping`), ShadowAPI (`shadow`, applied by
      whoever tests visibility): see those modules.

Sampling and MIS: `sample_light` returns solid-angle densities; rays that BSDF sampling sends get
the same density from `light_pdf`, their emitted radiance from `emitted_radiance`, and their hit
distance from `intersect_light`. Every technique is the same function of the direction, so
`sample_light(...).pdf == light_pdf(..., sample.direction)` (to rounding: rect and disk samples
take their hits from the sampled point, `planar_hits`). Delta lights (radius-0
sphere, angle-0 distant) set `is_delta`: their `radiance` is then the irradiance on a surface
facing the light (I / d^2 for the point light, L for the distant light) with pdf 1, and BSDF rays
never hit them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from pxr import UsdLux

from relight_torch.lights.dome import dome_samplers, latlong_direction, local_from_lookup, lookup_from_local
from relight_torch.lights.geometry import (
    LightFrame,
    SurfaceHits,
    check_extent,
    check_transform,
    intersect_surface,
    planar_hits,
    sample_area_local,
    surface_area,
    world_radius,
)
from relight_torch.lights.image import image_tensors, lookup_bilinear
from relight_torch.lights.light import Light, LightKind
from relight_torch.lights.shaping import emission_factor
from relight_torch.math.checks import check_last_dim
from relight_torch.math.frame import dot, length, orthonormal_basis, to_world
from relight_torch.math.sampling import concentric_disk, uniform_cone, uniform_sphere

_AREA_KINDS = (LightKind.SPHERE, LightKind.RECT, LightKind.DISK, LightKind.CYLINDER)

MAX_RADIANCE = 1e20
"""Largest radiance (nits) a light may emit into a lobe: intensity * 2^exposure * color [* blackbody]
[/ sizeFactor] * max(1, diffuse, specular) * the texture's largest texel. The sun's disc is about
1.6e9 nits; far above it the float32 kernels overflow once a BRDF peak and a solid angle multiply
in (a diffuse multiplier of 1e30 rendered inf pixels). A normalized distant light of a tiny angle
reaches it first: give it angle 0 (a delta light) instead."""


@dataclass(frozen=True)
class LightSample:
    """Samples of one light seen from N points, S samples each.

    Attributes:
        direction: (N, S, 3) unit world direction from the point towards the light.
        distance: (N, S) world distance to the emitting point; inf for distant and dome lights
            (and for samples that carry no light).
        radiance: (N, S, 3) radiance arriving along `direction` (shaping, texture and one-sidedness
            included); for a delta light the irradiance on a surface facing it.
        pdf: (N, S) solid-angle density of `direction`; 0 marks a sample that carries no light
            (the point is inside a sphere light, the light is dark); 1 for delta lights.
        is_delta: the light is a point or a zero-angle distant light.
    """

    direction: torch.Tensor
    distance: torch.Tensor
    radiance: torch.Tensor
    pdf: torch.Tensor
    is_delta: bool

    def weight(self) -> torch.Tensor:
        """(N, S, 3) radiance / pdf, 0 where pdf is 0: the Monte Carlo weight of each sample."""
        return self.radiance * self.inverse_pdf().unsqueeze(-1)

    def inverse_pdf(self) -> torch.Tensor:
        """(N, S) 1 / pdf, 0 where pdf is 0 (a sample carrying no light has zero radiance)."""
        safe_pdf = torch.where(self.pdf > 0, self.pdf, torch.ones_like(self.pdf))
        return (self.pdf > 0) / safe_pdf


def size_factor(light: Light) -> float:
    """The `normalize` divisor: world emitting area (area lights), the distant cone's factor, or 1 (dome)."""
    if light.kind in _AREA_KINDS:
        return surface_area(light)
    if light.kind is LightKind.DISTANT:
        theta_max = _distant_theta_max(light)
        if theta_max == 0.0:
            return 1.0
        sin2 = math.sin(theta_max) ** 2
        return math.pi * sin2 if theta_max <= math.pi / 2 else math.pi * (2.0 - sin2)
    return 1.0


def is_delta_light(light: Light) -> bool:
    """Point light (radius-0 sphere) or zero-angle distant light: only `sample_light` reaches it."""
    return (light.kind is LightKind.SPHERE and light.radius == 0.0) or (
        light.kind is LightKind.DISTANT and light.angle == 0.0
    )


def light_radiance_scale(light: Light) -> np.ndarray:
    """(3,) float64: intensity * 2^exposure * color [* blackbody] [/ sizeFactor].

    This is the radiance L of area, distant and (untextured) dome lights; for a radius-0 sphere it
    is the radiant intensity I (0 unless normalize, see the module doc). Zero-area rect, disk and
    cylinder lights emit nothing.
    """
    # np.exp2, not 2.0**: an exposure of 1e30 is inf here (refused by `validate_light`), not an OverflowError.
    scale: np.ndarray = light.intensity * np.exp2(light.exposure) * np.asarray(light.color, np.float64)
    if light.enable_color_temperature:
        scale = scale * np.asarray(UsdLux.BlackbodyTemperatureAsRgb(light.color_temperature), np.float64)
    if light.kind is LightKind.SPHERE and light.radius == 0.0:
        return scale / 4.0 if light.normalize else np.zeros(3)
    if light.kind in _AREA_KINDS and surface_area(light) == 0.0:
        return np.zeros(3)
    return scale / size_factor(light) if light.normalize else scale


def validate_light(light: Light) -> None:
    """Raise ValueError (one line naming the light) for what the samplers cannot honour.

    Checks the transform (`geometry.check_transform`), positions and sizes (`geometry.check_extent`),
    the emitted radiance (`MAX_RADIANCE`), the dome's pole axis, image shapes, and the Barzel
    fall-off ramps' order.
    """
    check_transform(light)
    check_extent(light)
    _check_radiance(light)
    if light.pole_axis not in ("Y", "Z"):
        raise ValueError(f"{light.path}: poleAxis must be 'Y' or 'Z' once resolved, got {light.pole_axis!r}")
    images = {"texture": light.texture, "cookie": light.barzel.cookie if light.barzel else None}
    for name, image in images.items():
        if image is not None and (image.ndim != 3 or image.shape[-1] != 3 or image.dtype != np.float32):
            raise ValueError(
                f"{light.path}: {name} must be an (H, W, 3) float32 array, got {image.dtype} {image.shape}"
            )
    barzel = light.barzel
    if barzel is not None:
        if barzel.near_end > 0 and not 0 <= barzel.near_start <= barzel.near_end:
            raise ValueError(
                f"{light.path}: relight:barzel:near:start must lie in [0, near:end], "
                f"got {barzel.near_start} and {barzel.near_end}"
            )
        if barzel.far_end >= 0 and not 0 <= barzel.far_start <= barzel.far_end:
            raise ValueError(
                f"{light.path}: relight:barzel:far:start must lie in [0, far:end], "
                f"got {barzel.far_start} and {barzel.far_end}"
            )


def _check_radiance(light: Light) -> None:
    """Raise ValueError naming the light's emission inputs when its peak radiance exceeds `MAX_RADIANCE`."""
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        scale = light_radiance_scale(light)
        peak = float(np.max(scale)) * max(1.0, light.diffuse, light.specular)
        if light.texture is not None and light.texture.size:
            peak *= max(1.0, float(np.max(light.texture)))
    if not peak <= MAX_RADIANCE:
        raise ValueError(
            f"{light.path}: inputs:intensity * 2^inputs:exposure * inputs:color (with normalize, diffuse, specular "
            f"and texture) emits {peak:g} nits, beyond {MAX_RADIANCE:g}"
        )


def sample_light(light: Light, points: torch.Tensor, u: torch.Tensor) -> LightSample:
    """Sample directions towards a light (solid-angle densities; see the module doc).

    Sphere: uniform over the visible cap (the cone it subtends); rect, disk, cylinder: uniform
    area; distant: uniform cone of half-angle angle/2; dome: lat-long luminance x sin(theta)
    importance sampling (uniform sphere when untextured).

    Args:
        light: the light.
        points: (N, 3) world receiver positions.
        u: (N, S, 2) uniform numbers in [0, 1), same device and dtype as `points` (and the results).

    Returns:
        LightSample with (N, S) leading dimensions. The work runs with the samples leading, (S, N),
        so that per-point values broadcast over whole slabs (torch's CPU kernels vectorise that;
        a broadcast over the middle axis of (N, S, 3) runs 10-30x slower): the results are
        (N, S, ...) views of (S, N, ...) memory. u laid out that way too (a transposed (S, N, 2)
        tensor, see `light_samples.fixed_light_samples`) is read without a copy.
    """
    check_last_dim(points, 3, "points")
    check_last_dim(u, 2, "u")
    if u.dtype != points.dtype or u.shape[:-2] != points.shape[:-1]:
        raise ValueError(
            f"u must be (N, S, 2) of the points' dtype {points.dtype} for points {tuple(points.shape)}; "
            f"got {u.dtype} {tuple(u.shape)}"
        )
    u = u.movedim(-2, 0).contiguous()
    receivers = points.unsqueeze(0)
    frame = LightFrame.of(light, points)
    if is_delta_light(light):
        sample = _sample_delta(light, frame, receivers, u)
    elif light.kind in (LightKind.RECT, LightKind.DISK):
        disk_points = concentric_disk(u)[0] if light.kind is LightKind.DISK else None
        directions, hits = planar_hits(light, frame, receivers, sample_area_local(light, disk_points, u))
        sample = LightSample(directions, *_trace(light, frame, receivers, directions, hits), False)
    else:
        directions = _sample_directions(light, frame, receivers, u)
        sample = LightSample(directions, *_trace(light, frame, receivers, directions), False)
    return LightSample(
        sample.direction.movedim(0, -2),
        sample.distance.movedim(0, -1),
        sample.radiance.movedim(0, -2),
        sample.pdf.movedim(0, -1),
        sample.is_delta,
    )


def _sample_directions(light: Light, frame: LightFrame, receivers: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """(S, N, 3) unit world directions from receivers (1, N, 3) towards a sphere, distant, dome or
    cylinder light, u (S, N, 2) (rect and disk samples: `planar_hits`)."""
    if light.kind is LightKind.SPHERE:
        to_centre = frame.origin - receivers
        distance = length(to_centre)
        sin2_max = (world_radius(light) / distance).square()
        cos_max = torch.where(sin2_max < 1.0, torch.sqrt((1.0 - sin2_max).clamp_min(0.0)), -1.0)
        return _cone_directions(u, torch.nn.functional.normalize(to_centre, dim=-1), cos_max)
    if light.kind is LightKind.DISTANT:
        cos_max = torch.full_like(u[..., 0], math.cos(_distant_theta_max(light)))
        return _cone_directions(u, _to_distant_light(frame).expand_as(receivers), cos_max)
    if light.kind is LightKind.DOME:
        return _dome_directions(light, frame, u)
    emitting_points = frame.point_to_world(sample_area_local(light, None, u))  # the cylinder
    return torch.nn.functional.normalize(emitting_points - receivers, dim=-1)


def emitted_radiance(light: Light, points: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Radiance (..., 3) arriving at `points` (..., 3) from the light along unit `directions` (..., 3).

    Shapes broadcast. 0 where the ray misses the light or meets its back; delta lights give 0.
    Occlusion by the scene is the caller's business (compare with `intersect_light`).
    """
    return _checked_trace(light, points, directions)[1]


def trace_light(
    light: Light, points: torch.Tensor, directions: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`intersect_light` (...), `emitted_radiance` (..., 3) and `light_pdf` (...) along the same
    `directions`, traced once."""
    return _checked_trace(light, points, directions)


def light_pdf(light: Light, points: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Solid-angle density (...) with which `sample_light` picks `directions` (..., 3) from `points` (..., 3)."""
    return _checked_trace(light, points, directions)[2]


def intersect_light(light: Light, origins: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """World distance (...) from `origins` (..., 3) along unit `directions` (..., 3) to the light's surface.

    inf on a miss (the back of a one-sided light counts as a miss: lights are not occluders), and
    always inf for distant and dome lights, which every ray leaving the scene reaches (whether it
    carries light: `emitted_radiance`).
    """
    return _checked_trace(light, origins, directions)[0]


def _checked_trace(
    light: Light, points: torch.Tensor, directions: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    check_last_dim(points, 3, "points")
    check_last_dim(directions, 3, "directions")
    return _trace(light, LightFrame.of(light, directions), points, directions)


def _trace(
    light: Light, frame: LightFrame, points: torch.Tensor, directions: torch.Tensor, hits: SurfaceHits | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(distance (...), radiance (..., 3), pdf (...)) of rays from `points` along `directions`.

    `points` stay unbroadcast, so that per-point work is done once per point. `hits`: the rays'
    hits on a rect or disk light when known (`planar_hits`), else they are intersected.
    """
    batch = torch.broadcast_shapes(  # type: ignore[no-untyped-call]  # unannotated in torch
        points.shape, directions.shape
    )
    directions = directions.expand(batch)
    scale = torch.as_tensor(light_radiance_scale(light), device=directions.device, dtype=directions.dtype)
    miss = torch.full_like(directions[..., 0], math.inf)
    if is_delta_light(light) or not bool((scale > 0).any()):
        return miss, torch.zeros_like(directions), torch.zeros_like(miss)
    if light.kind is LightKind.DOME:
        return miss, *_dome_radiance_pdf(light, frame, directions, scale)
    if light.kind is LightKind.DISTANT:
        cos_max = math.cos(_distant_theta_max(light))
        inside = (directions * _to_distant_light(frame)).sum(-1) >= cos_max
        pdf = torch.where(inside, 1.0 / (2.0 * math.pi * _one_minus_cos(_distant_theta_max(light))), 0.0)
        return miss, scale * inside.unsqueeze(-1), pdf
    if light.kind is LightKind.SPHERE:
        distance, pdf = _sphere_hits(light, frame, points, directions)
        texture: torch.Tensor | float = 1.0
    else:
        hits = intersect_surface(light, frame, points, directions) if hits is None else hits
        distance, pdf = hits.distance, hits.pdf
        has_texture = light.kind is LightKind.RECT and light.texture is not None
        texture = _rect_texture(light, hits.point_local) if has_texture else 1.0
        distance = torch.where(hits.cos_light > 0, distance, math.inf)
    lit = (distance < math.inf).unsqueeze(-1)  # distances are >= 0: finite
    factor: torch.Tensor | float | None = _shape(light, frame, -directions, points)
    if factor is None and not torch.is_tensor(texture):  # a constant: a multiply, not a 3-channel where
        return distance, lit * scale, pdf
    factor = texture if factor is None else factor * texture
    return distance, torch.where(lit, scale * factor, 0.0), pdf


def _shape(
    light: Light, frame: LightFrame, emission_world: torch.Tensor, receivers: torch.Tensor
) -> torch.Tensor | None:
    """(..., 3) ShapingAPI x Barzel factor of an area light for world emission directions (..., 3);
    None when neither applies."""
    if light.shaping is None and light.barzel is None:
        return None
    emission_local = torch.nn.functional.normalize(frame.vector_to_local(emission_world), dim=-1)
    return emission_factor(light, emission_local, receivers, frame.origin)


def _sphere_hits(
    light: Light, frame: LightFrame, points: torch.Tensor, directions: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(distance inf on a miss, cap-sampling pdf) of rays from outside a sphere light."""
    radius = world_radius(light)
    to_centre = frame.origin - points
    along = dot(to_centre, directions)
    # The perpendicular offset from the ray, not d^2 - along^2, keeps small caps accurate (pbrt-v4).
    offset = [(to_centre[..., i] - along * directions[..., i]).square() for i in range(3)]
    offset2 = offset[0] + offset[1] + offset[2]
    discriminant = radius**2 - offset2
    centre_distance2 = dot(to_centre, to_centre)
    hit = (discriminant >= 0) & (centre_distance2 > radius**2) & (along > 0)
    distance = torch.where(hit, along - torch.sqrt(discriminant.clamp_min(0.0)), math.inf)
    sin2_max = (radius**2 / centre_distance2).clamp(max=1.0)
    one_minus_cos = sin2_max / (1.0 + torch.sqrt(1.0 - sin2_max))
    pdf = torch.where(hit, 1.0 / (2.0 * math.pi * one_minus_cos.clamp_min(torch.finfo(one_minus_cos.dtype).tiny)), 0.0)
    return distance, pdf


def _rect_texture(light: Light, point_local: torch.Tensor) -> torch.Tensor:
    """(..., 3) rect light texture at local hit points (..., 3): pixel (0, 0) at (+X, +Y)."""
    assert light.texture is not None  # the caller checks
    st = torch.stack((0.5 - point_local[..., 0] / light.width, 0.5 + point_local[..., 1] / light.height), dim=-1)
    return lookup_bilinear(image_tensors.get(light.texture, point_local.device, point_local.dtype), st)


def _dome_radiance_pdf(
    light: Light, frame: LightFrame, directions: torch.Tensor, scale: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(radiance (..., 3), pdf (...)) of a dome light along world directions (..., 3)."""
    if light.texture is None:
        return scale.expand_as(directions), torch.full_like(directions[..., 0], 0.25 / math.pi)
    lookup = lookup_from_local(
        torch.nn.functional.normalize(frame.vector_to_local(directions), dim=-1), light.pole_axis
    )
    sampler = dome_samplers.get(light.texture, directions.device, directions.dtype)
    return scale * sampler.radiance(lookup), sampler.pdf(lookup)


def _dome_directions(light: Light, frame: LightFrame, u: torch.Tensor) -> torch.Tensor:
    """(S, N, 3) world directions towards a dome light from u (S, N, 2), importance-sampled when textured."""
    if light.texture is None:
        directions_local, _ = uniform_sphere(u)
    else:
        sampler = dome_samplers.get(light.texture, u.device, u.dtype)
        directions_local = local_from_lookup(latlong_direction(*sampler.sample_uv(u)), light.pole_axis)
    return torch.nn.functional.normalize(frame.vector_to_world(directions_local), dim=-1)


def _sample_delta(light: Light, frame: LightFrame, receivers: torch.Tensor, u: torch.Tensor) -> LightSample:
    """Point or zero-angle distant light: one direction per point, repeated S times; receivers
    (1, N, 3), u (S, N, 2), results (S, N, ...)."""
    scale = torch.as_tensor(light_radiance_scale(light), device=u.device, dtype=u.dtype)
    ones = torch.ones_like(u[..., 0])
    if light.kind is LightKind.DISTANT:
        direction = _to_distant_light(frame) * ones.unsqueeze(-1)
        return LightSample(direction, ones * math.inf, scale * ones.unsqueeze(-1), ones, True)
    to_light = (frame.origin - receivers) * ones.unsqueeze(-1)
    distance = length(to_light)
    direction = to_light / distance.unsqueeze(-1)
    factor = _shape(light, frame, -direction, receivers)
    irradiance = (scale if factor is None else scale * factor) / distance.square().unsqueeze(-1)
    return LightSample(direction, distance, irradiance, ones, True)


def _cone_directions(u: torch.Tensor, axis: torch.Tensor, cos_max: torch.Tensor) -> torch.Tensor:
    """Uniform directions (S, N, 3) in cones around unit world axes (1, N, 3) or (S, N, 3).

    The warp runs in float64: a small cap (a distant sun, a far sphere) has 1 - cos_max below
    float32's resolution near 1, which would misplace its edge.
    """
    local, _ = uniform_cone(u.to(torch.float64), cos_max.to(torch.float64))
    tangent, bitangent = orthonormal_basis(axis)
    return to_world(local.to(u.dtype), tangent, bitangent, axis)


def _to_distant_light(frame: LightFrame) -> torch.Tensor:
    """(3,) unit world direction towards a distant light: its local +Z (it shines along -Z)."""
    return torch.nn.functional.normalize(frame.world_from_light[:, 2], dim=-1)


def _distant_theta_max(light: Light) -> float:
    """thetaMax = clamp(radians(angle) / 2, 0, pi): the distant light's half-angle."""
    return min(max(math.radians(light.angle) / 2.0, 0.0), math.pi)


def _one_minus_cos(theta: float) -> float:
    """1 - cos(theta) without cancellation for small angles."""
    return 2.0 * math.sin(0.5 * theta) ** 2
