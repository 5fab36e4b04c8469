"""Angular and distance shaping of an area light's emission: UsdLux ShapingAPI and our Barzel API.

Both act on the emission direction in the light's frame: e (..., 3), unit, from the emitting point
towards the receiver, where the light's axis is -Z. Formulas: USD_EXR_NOTES 1.3 (the 26.11 schema
text, as hdEmbree implements it) and relight_torch/schemas/schema.usda (RelightBarzelLightAPI).
"""

from __future__ import annotations

import math

import torch

from relight_torch.lights.image import image_tensors, lookup_bilinear
from relight_torch.lights.light import BarzelShaping, Light, Shaping


def smoothstep(edge0: float, edge1: float, x: torch.Tensor) -> torch.Tensor:
    """Hermite step from 0 at edge0 to 1 at edge1; a hard step (x > edge0) when the edges meet."""
    if edge1 <= edge0:
        return (x > edge0).to(x.dtype)
    t = ((x - edge0) / (edge1 - edge0)).clamp(0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def linear_step(edge0: float, edge1: float, x: torch.Tensor) -> torch.Tensor:
    """Linear ramp from 0 at edge0 to 1 at edge1; a hard step (x > edge0) when the edges meet."""
    if edge1 <= edge0:
        return (x > edge0).to(x.dtype)
    return ((x - edge0) / (edge1 - edge0)).clamp(0.0, 1.0)


def shaping_factor(shaping: Shaping, emission_local: torch.Tensor) -> torch.Tensor:
    """UsdLux ShapingAPI factor (focus, focus tint, cone with softness; IES not supported).

    cos_off = dot(e, -Z); focus: |cos_off|^focus (focus <= 0: 1), tinted as
    focusTint + focus_factor (1 - focusTint); cone: 1 - smoothstep(theta_cut (1 - softness),
    theta_cut, theta_off) with theta_cut = radians(coneAngle), the HALF-angle, softness clamped to
    [0, 1].

    Args:
        shaping: the applied ShapingAPI values.
        emission_local: (..., 3) unit emission directions in the light's frame.

    Returns:
        (..., 3) RGB factor.
    """
    cos_off = (-emission_local[..., 2]).clamp(-1.0, 1.0)
    focus = cos_off.abs() ** shaping.focus if shaping.focus > 0 else torch.ones_like(cos_off)
    tint = torch.as_tensor(shaping.focus_tint, device=cos_off.device, dtype=cos_off.dtype)
    # Written so that the cone angle, softness and focus may be 0-d tensors requiring grad (`relight
    # solve` differentiates through them): no math.radians or min/max, which would make floats.
    theta_cut = shaping.cone_angle * (math.pi / 180.0)
    softness = shaping.cone_softness
    softness = softness.clamp(0.0, 1.0) if torch.is_tensor(softness) else min(max(softness, 0.0), 1.0)
    theta_start = theta_cut * (1.0 - softness)
    cone = 1.0 - smoothstep(theta_start, theta_cut, torch.acos(cos_off))
    return (tint + focus.unsqueeze(-1) * (1.0 - tint)) * cone.unsqueeze(-1)


def barzel_factor(barzel: BarzelShaping, emission_local: torch.Tensor, receiver_distance: torch.Tensor) -> torch.Tensor:
    """RelightBarzelLightAPI factor: window, barn doors, cookie, near/far fall-off.

    With p = (e.x, e.y) / -e.z the direction's point on the plane one unit in front of the light:
    window: 1 - smoothstep(1 - edge, 1, q), q = (|2 p.x / width|^n + |2 p.y / height|^n)^(1/n),
    n = 2 / roundness (roundness 0: q = max of the two), and 0 behind the light (e.z >= 0);
    barn doors: 0 where atan2(e.x, -e.z) exceeds `right` or falls below -`left` (degrees), and
    likewise atan2(e.y, -e.z) against `top` / `bottom`;
    cookie: the image at st = 0.5 + (p - offset) / (2 scale), 0 outside it and behind the light;
    near: ramp(near_start, near_end, distance); far: 1 - ramp(far_start, far_end, distance), the
    ramp smoothstep or linear per `falloff_smooth`.

    Args:
        barzel: the applied RelightBarzelLightAPI values.
        emission_local: (..., 3) unit emission directions in the light's frame.
        receiver_distance: (...) world distance from the light's origin to the receiver.

    Returns:
        (..., 3) RGB factor.
    """
    x, y, z = emission_local.unbind(-1)
    factor = torch.ones_like(x)
    in_front = z < 0
    projected = emission_local[..., :2] / torch.where(in_front, -z, torch.ones_like(z)).unsqueeze(-1)
    if barzel.window_enable:
        qx = (2.0 * projected[..., 0] / barzel.window_width).abs()
        qy = (2.0 * projected[..., 1] / barzel.window_height).abs()
        if barzel.window_roundness > 0:
            exponent = 2.0 / barzel.window_roundness
            q = (qx**exponent + qy**exponent) ** (1.0 / exponent)
        else:
            q = torch.maximum(qx, qy)
        edge = min(max(barzel.window_edge, 0.0), 1.0)
        factor = factor * (1.0 - smoothstep(1.0 - edge, 1.0, q)) * in_front
    horizontal = torch.rad2deg(torch.atan2(x, -z))
    vertical = torch.rad2deg(torch.atan2(y, -z))
    factor = factor * (
        (horizontal <= barzel.barn_door_right)
        & (horizontal >= -barzel.barn_door_left)
        & (vertical <= barzel.barn_door_top)
        & (vertical >= -barzel.barn_door_bottom)
    )
    ramp = smoothstep if barzel.falloff_smooth else linear_step
    if barzel.near_end > 0:
        factor = factor * ramp(barzel.near_start, barzel.near_end, receiver_distance)
    if barzel.far_end >= 0:
        factor = factor * (1.0 - ramp(barzel.far_start, barzel.far_end, receiver_distance))
    factor = factor.unsqueeze(-1).expand(*factor.shape, 3)
    if barzel.cookie is not None:
        cookie = image_tensors.get(barzel.cookie, x.device, x.dtype)
        offset = torch.as_tensor(barzel.cookie_offset, device=x.device, dtype=x.dtype)
        scale = torch.as_tensor(barzel.cookie_scale, device=x.device, dtype=x.dtype)
        st = 0.5 + (projected - offset) / (2.0 * scale)
        factor = factor * lookup_bilinear(cookie, st) * in_front.unsqueeze(-1)
    return factor


def emission_factor(
    light: Light, emission_local: torch.Tensor, receivers: torch.Tensor, origin: torch.Tensor
) -> torch.Tensor | None:
    """ShapingAPI x Barzel factor (..., 3) of a light for unit emission directions in its frame.

    Args:
        light: the light (its `shaping` and `barzel`, either may be None).
        emission_local: (..., 3) unit directions from the light towards the receivers, light space.
        receivers: (..., 3) world receiver positions (broadcasting against `emission_local`), used
            only by the Barzel near/far fall-off.
        origin: (3,) the light's world origin.

    Returns:
        The factor, or None when neither control applies (the caller skips the multiply).
    """
    factor = None
    if light.shaping is not None:
        factor = shaping_factor(light.shaping, emission_local)
    if light.barzel is not None:
        barzel = barzel_factor(light.barzel, emission_local, (receivers - origin).norm(dim=-1))
        factor = barzel if factor is None else factor * barzel
    return factor
