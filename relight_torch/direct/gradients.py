"""The direct relighter differentiated in a light's position, orientation, size and shaping.

`relight solve` (`relight_torch.solve`) moves lights by gradient descent through this module. A
light's image is the relighter's per-light shading written as one differentiable expression:

    image = to_image( sum_s f(E, L_s) cos(theta_s) L_s V_s / (pdf_s S) )

with the same light samples (`sample_light`, fixed stratified numbers per point), BRDF
(`preview_surface.split`), ShadowAPI factor, light link mask, box filter and camera exposure as
the relighter. The light's parameters are tensors (`LightPose`); they reach the light code in
two ways, so that `relight_torch.lights` stays written once for numbers and tensors alike:

- size (radius, width, height, length) and shaping (cone angle, softness, focus) are put into the
  `Light` as 0-d tensors: the sampling, area, density and shaping functions are written with
  arithmetic that keeps them tensors;
- position and orientation move the receivers instead of the light: a light at origin c rotated
  by R (world frame, about its origin) seen from point p looks as the starting light (origin c0)
  seen from R^T (p - c) + c0, so the light's transform stays the starting numpy matrix and the
  gradient flows through the points; directions come back to the world as R d.

Visibility is not differentiable (a shadow ray hits or misses): `freeze_visibility` traces the
shadow rays of the current parameters once, without gradient, and `light_image` holds that
factor fixed. The solver refreshes it between iterations, so an iteration's gradient ignores the
motion of shadow edges (their effect enters through the next iteration's visibility). The
estimator is the relighter's plain Monte Carlo sum: it does not apply the ratio estimator or the
visibility filter of rect lights (`lights.polygon`), so it differs from `Relighter.light_image`
by sampling noise of the same order as the relighter's own.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from relight_torch.brdf import preview_surface
from relight_torch.lights.emission import LightSample, is_delta_light, sample_light
from relight_torch.lights.light import Light, LightKind
from relight_torch.lights.shadow import shadow_factor
from relight_torch.math.frame import dot, to_local
from relight_torch.visibility import Visibility

if TYPE_CHECKING:
    from relight_torch.direct.relighter import Relighter

GEOMETRY_KINDS = ("position", "orientation", "size", "shaping")
"""The `--free` kinds this module differentiates (the colour kinds need no gradient through shading)."""

SIZE_FIELDS: dict[LightKind, tuple[str, ...]] = {
    LightKind.SPHERE: ("radius",),
    LightKind.DISK: ("radius",),
    LightKind.RECT: ("width", "height"),
    LightKind.CYLINDER: ("radius", "length"),
}
"""The `Light` fields the 'size' kind frees, per light kind (local units, before the transform's scale)."""

SHAPING_FIELDS = ("cone_angle", "cone_softness", "focus")
"""The `Shaping` fields the 'shaping' kind frees (the focus tint stays)."""

_POSITIONED = (LightKind.SPHERE, LightKind.RECT, LightKind.DISK, LightKind.CYLINDER)
_ORIENTED = (LightKind.RECT, LightKind.DISK, LightKind.CYLINDER, LightKind.DISTANT)


def applies(kind: str, light: Light) -> bool:
    """Whether free-parameter `kind` (one of GEOMETRY_KINDS) means something for `light`.

    position: sphere, rect, disk, cylinder; orientation: rect, disk, cylinder, distant, and a
    sphere with ShapingAPI; size: the kinds of SIZE_FIELDS; shaping: an area light with ShapingAPI
    applied. Dome lights take none (their samples are importance-sampled from the texture).
    """
    if kind == "position":
        return light.kind in _POSITIONED
    if kind == "orientation":
        return light.kind in _ORIENTED or (light.kind is LightKind.SPHERE and light.shaping is not None)
    if kind == "size":
        return light.kind in SIZE_FIELDS and not is_delta_light(light)
    if kind == "shaping":
        return light.shaping is not None and light.kind in _POSITIONED
    raise ValueError(f"unknown geometry kind {kind!r} (expected one of {', '.join(GEOMETRY_KINDS)})")


def rotation_matrix(rotation: torch.Tensor) -> torch.Tensor:
    """(3, 3) rotation of an axis-angle vector (3,) in radians (the exponential of its skew matrix)."""
    x, y, z = rotation.unbind(-1)
    zero = torch.zeros_like(x)
    skew = torch.stack((torch.stack((zero, -z, y)), torch.stack((z, zero, -x)), torch.stack((-y, x, zero))))
    return torch.linalg.matrix_exp(skew)


@dataclass
class LightPose:
    """One light's free geometry as tensors (each may require grad), in world units and degrees.

    Attributes:
        position: (3,) world origin of the light.
        rotation: (3,) axis-angle (radians) of a world-frame rotation about the light's origin,
            applied on top of the starting orientation: zeros at the start.
        size: (K,) the light's SIZE_FIELDS values (local units), or None for a kind without one.
        shaping: (3,) cone angle (degrees, the half-angle), cone softness and focus, or None
            without ShapingAPI.
    """

    position: torch.Tensor
    rotation: torch.Tensor
    size: torch.Tensor | None
    shaping: torch.Tensor | None

    @staticmethod
    def of(light: Light, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> LightPose:
        """The pose of `light` as it stands (no rotation on top)."""

        def tensor(values: object) -> torch.Tensor:  # a copy: never a view of the light's arrays
            return torch.tensor(np.array(values, np.float64), dtype=dtype, device=device)

        fields = SIZE_FIELDS.get(light.kind)
        shaping = light.shaping
        return LightPose(
            tensor(light.world_from_light[:3, 3]),
            tensor(np.zeros(3)),
            None if fields is None else tensor([getattr(light, name) for name in fields]),
            None if shaping is None else tensor([getattr(shaping, name) for name in SHAPING_FIELDS]),
        )

    def detached(self) -> LightPose:
        """The same values, no longer part of a graph."""
        return self.map(lambda t: t.detach().clone())

    def tensors(self) -> tuple[torch.Tensor | None, ...]:
        """(position, rotation, size, shaping), the same tensor objects (no copy)."""
        return (self.position, self.rotation, self.size, self.shaping)

    def map(self, function: Callable[[torch.Tensor], torch.Tensor]) -> LightPose:
        """A pose of `function` applied to each tensor (None stays None)."""
        size = None if self.size is None else function(self.size)
        shaping = None if self.shaping is None else function(self.shaping)
        return LightPose(function(self.position), function(self.rotation), size, shaping)

    def tensor_light(self, light: Light) -> Light:
        """`light` with its size and shaping fields replaced by this pose's 0-d tensors (transform
        untouched: position and orientation act on the receivers, see the module doc)."""
        changes: dict[str, Any] = {}  # 0-d tensors where the fields say float (module doc)
        if self.size is not None:
            changes.update(zip(SIZE_FIELDS[light.kind], self.size.unbind(), strict=True))
        if self.shaping is not None and light.shaping is not None:
            shaping: dict[str, Any] = dict(zip(SHAPING_FIELDS, self.shaping.unbind(), strict=True))
            changes["shaping"] = dataclasses.replace(light.shaping, **shaping)
        return dataclasses.replace(light, **changes)

    def posed_light(self, light: Light) -> Light:
        """`light` moved, turned, sized and shaped to this pose's values, as plain numbers."""
        world_from_light = np.array(light.world_from_light, dtype=np.float64, copy=True)
        turn = rotation_matrix(self.rotation.detach().to(torch.float64).cpu()).numpy()
        world_from_light[:3, :3] = turn @ world_from_light[:3, :3]
        world_from_light[:3, 3] = self.position.detach().to(torch.float64).cpu().numpy()
        changes: dict[str, Any] = {"world_from_light": world_from_light}
        if self.size is not None:
            changes.update(zip(SIZE_FIELDS[light.kind], self.size.detach().cpu().tolist(), strict=True))
        if self.shaping is not None and light.shaping is not None:
            changes["shaping"] = dataclasses.replace(
                light.shaping, **dict(zip(SHAPING_FIELDS, self.shaping.detach().cpu().tolist(), strict=True))
            )
        return dataclasses.replace(light, **changes)


@dataclass(frozen=True)
class FrozenVisibility:
    """A light's shadow factor at one pose, held fixed while its parameters are differentiated.

    Attributes:
        factor: (S, N, 3) ShadowAPI shadow factor of each light sample at each shading point
            (1 where the sample is visible), without gradient.
    """

    factor: torch.Tensor


def frozen_visibility(
    visibility: Visibility, light: Light, pose: LightPose, points: torch.Tensor, normals: torch.Tensor, u: torch.Tensor
) -> FrozenVisibility:
    """Trace the shadow rays of `light` at `pose` from N points once (no gradient).

    Args:
        visibility: the shadow queries (the relighter's).
        light: the light as it started (its transform is the pose's reference).
        pose: the parameters to trace at.
        points: (N, 3) world receivers; normals: (N, 3) their geometric normals (ray offsets).
        u: (N, S, 2) the fixed light-sample numbers of the points.
    """
    with torch.no_grad():
        detached = pose.detached()
        direction, sample = _sample(light, detached, points, u)
        # The shadow rays of the moved light (its own transform, for shadow maps and shadow links).
        distance = visibility.occluder_distance(
            detached.posed_light(light), points, normals, direction.transpose(0, 1), sample.distance
        ).transpose(0, 1)
        return FrozenVisibility(shadow_factor(light.shadow, distance < torch.inf, distance))


def freeze_visibility(relighter: Relighter, light: Light, pose: LightPose, num_samples: int) -> FrozenVisibility:
    """`frozen_visibility` at the relighter's shading points, with its fixed light samples."""
    g = relighter.gbuffer
    return frozen_visibility(
        relighter.visibility, light, pose, g.position, g.geometric_normal, relighter.fixed_samples(num_samples)
    )


def light_image(relighter: Relighter, light: Light, pose: LightPose, visibility: FrozenVisibility) -> torch.Tensor:
    """(H, W, 3) image of the unit light (intensity 1, exposure 0, white, no temperature; diffuse
    and specular multipliers and light link applied) at `pose`, differentiable in the pose's tensors.

    Args:
        relighter: the direct `Relighter` whose G-buffer is shaded.
        light: the light as it started; its colour fields are ignored.
        pose: the parameters (tensors of the G-buffer's dtype and device, or castable to them).
        visibility: `freeze_visibility` of the same light, held fixed.
    """
    g = relighter.gbuffer
    num_samples = visibility.factor.shape[0]
    direction, sample = _sample(light, pose, g.position, relighter.fixed_samples(num_samples))
    # (S, N, ...) throughout: per-point values broadcast over the samples' slabs.
    cosine = dot(direction, g.normal)
    facing = dot(direction, g.geometric_normal) > 0
    scalar = sample.inverse_pdf().transpose(0, 1) * ((cosine > 0) & facing) * (cosine / num_samples)
    weight = sample.radiance.transpose(0, 1) * scalar.unsqueeze(-1) * visibility.factor
    frame = (g.tangent, g.bitangent, g.normal)
    diffuse, specular = preview_surface.split(g.params, to_local(g.wo_world(), *frame), to_local(direction, *frame))
    per_point = ((diffuse * light.diffuse + specular * light.specular) * weight).sum(0)
    mask = relighter.light_mask(light)
    if mask is not None:
        per_point = per_point * mask
    return relighter.to_image(per_point)


def diffuse_light(
    light: Light,
    pose: LightPose,
    points: torch.Tensor,
    normals: torch.Tensor,
    albedo: torch.Tensor,
    u: torch.Tensor,
    visibility: FrozenVisibility,
) -> torch.Tensor:
    """(N, 3) radiance leaving N diffuse points after one reflection of the unit light at `pose`,
    differentiable in the pose: `diffuse_light.diffuse_radiance`'s estimator (diffuse x albedo / pi
    x irradiance from the fixed samples, on the side `normals` point to) without its ratio
    estimator, visibility frozen.

    Args:
        light: the light as it started; pose: its parameters.
        points: (N, 3) world points; normals: (N, 3) unit receiving normals; albedo: (N, 3).
        u: (N, S, 2) fixed light-sample numbers; visibility: `frozen_visibility` at these points.
    """
    direction, sample = _sample(light, pose, points, u)
    cosine = dot(direction, normals).clamp(min=0.0)
    irradiance = (sample.weight().transpose(0, 1) * cosine.unsqueeze(-1) * visibility.factor).mean(0)
    return light.diffuse * albedo / math.pi * irradiance


def _sample(light: Light, pose: LightPose, points: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, LightSample]:
    """World directions (S, N, 3) from `points` (N, 3) to the unit light's samples at `pose`
    (fixed numbers u (N, S, 2)), and the `LightSample` (N, S) seen from the receivers moved into
    the starting light's frame (module doc)."""
    pose = pose.map(lambda t: t.to(points.device, points.dtype))
    turn = rotation_matrix(pose.rotation)
    origin = torch.as_tensor(light.world_from_light[:3, 3], device=points.device, dtype=points.dtype)
    receivers = (points - pose.position) @ turn + origin  # rows: R^T (p - c) + c0
    unit = dataclasses.replace(
        pose.tensor_light(light), intensity=1.0, exposure=0.0, color=(1.0, 1.0, 1.0), enable_color_temperature=False
    )
    sample = sample_light(unit, receivers, u)
    direction = sample.direction.transpose(0, 1) @ turn.T  # rows: R d
    return direction, sample
