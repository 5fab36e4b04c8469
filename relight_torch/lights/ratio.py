"""The lights whose unshadowed irradiance has a closed form, and the ratio estimator built on it.

Ratio estimator (Heitz, Hill & McGuire 2018, "Combining analytic direct illumination and
stochastic shadows"): with fixed light samples, the diffuse term sum_s f L V cos / (pdf S) is
multiplied per receiver by G / G_hat, G the closed-form cosine-weighted solid angle of the light
and G_hat the same samples' unshadowed estimate sum_s cos / (pdf S) of it. Exact where the light
is wholly visible or wholly hidden; noise only in penumbrae. Per-sample multipliers applied
afterwards (ShapingAPI, Barzel) keep it consistent: the result tends to the integral of the
shaped emission as samples grow.

Lights with a closed form: untextured RectLights (Lambert's polygon formula, `polygon`),
SphereLights of positive radius (the projected solid angle of the visible cap, `sphere_cap`) and
DomeLights (the tabulated irradiance of their image, `dome_irradiance`). A textured dome's L varies
by direction, so its G and G_hat weigh each direction by the luminance of L over that of the
light's scale: the factor then corrects the diffuse sum's luminance exactly, and its colour is the
samples'. `normalize` scales L only, so it leaves G / G_hat unchanged. Every user of the closed form (the
direct relighter, the indirect methods' light on their samples, the multiview caching samples)
comes through `closed_form` here; the reference path tracer keeps sampling the same lights, and
tests hold the two to each other.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from relight_torch.lights.dome import REC709_LUMINANCE, lookup_from_local
from relight_torch.lights.dome_irradiance import DomeIrradiance
from relight_torch.lights.emission import light_radiance_scale
from relight_torch.lights.geometry import LightFrame
from relight_torch.lights.image import ArrayTensorCache
from relight_torch.lights.light import Light, LightKind
from relight_torch.lights.polygon import has_rect_closed_form, rect_cosine_integral
from relight_torch.lights.sphere_cap import has_sphere_closed_form, sphere_cosine_integral

dome_irradiances = ArrayTensorCache(DomeIrradiance.build, max_entries=4)


def has_closed_form(light: Light) -> bool:
    """Whether `closed_form` gives the light's unshadowed irradiance per unit radiance."""
    return has_rect_closed_form(light) or has_sphere_closed_form(light) or _luminance_weights(light) is not None


def _luminance_weights(light: Light) -> np.ndarray | None:
    """(3,) a dome's REC709 weights times its scale over the scale's luminance; None for
    another kind of light or a dome that emits no luminance."""
    if light.kind is not LightKind.DOME:
        return None
    weighted = np.asarray(REC709_LUMINANCE) * light_radiance_scale(light)
    return weighted / weighted.sum() if weighted.sum() > 0 else None


def estimate_weights(light: Light, distance: torch.Tensor, radiance: torch.Tensor) -> torch.Tensor:
    """(...) each sample's weight in G_hat, to multiply its cos / (pdf S): whether it reaches the
    emitting side (finite `distance` (...)), or for a dome the luminance of its `radiance` (..., 3)
    over the scale's (module doc)."""
    weights = _luminance_weights(light)
    if weights is None:
        return torch.isfinite(distance).to(radiance.dtype)
    scale = light_radiance_scale(light)
    per_channel = np.divide(weights, scale, out=np.zeros(3), where=scale != 0)
    return radiance @ torch.as_tensor(per_channel, device=radiance.device, dtype=radiance.dtype)


def closed_form(light: Light, points: torch.Tensor, normals: torch.Tensor) -> torch.Tensor | None:
    """G (N,) of the light at receivers (N, 3) with normals (N, 3); None without a closed form."""
    if not has_closed_form(light):
        return None
    if light.kind is LightKind.SPHERE:
        return sphere_cosine_integral(light, points, normals)
    if light.kind is LightKind.DOME:
        return _dome_integral(light, normals)
    return rect_cosine_integral(light, points, normals)


def _dome_integral(light: Light, normals: torch.Tensor) -> torch.Tensor:
    """(N,) a dome's luminance-weighted G at normals (N, 3): pi |n| for an untextured one.

    The integrand max(0, n.w) is linear in |n|, so a normal stored a little off unit length (half
    floats) scales G as it scales the samples' cosines: the ratio stays exact."""
    weights = _luminance_weights(light)
    assert weights is not None  # a dome with a closed form
    length = torch.sqrt((normals * normals).sum(-1))
    if light.texture is None:
        return length.mul(math.pi)
    local = LightFrame.of(light, normals).vector_to_local(normals)
    lookup = lookup_from_local(torch.nn.functional.normalize(local, dim=-1), light.pole_axis)
    irradiance = dome_irradiances.get(light.texture, normals.device, normals.dtype).irradiance(lookup)
    return (irradiance @ torch.as_tensor(weights, device=normals.device, dtype=normals.dtype)).mul_(length)


def ratio_of(exact: torch.Tensor, estimate: torch.Tensor) -> torch.Tensor:
    """(N,) exact / estimate, 1 where the estimate is 0 (no sample to carry visibility)."""
    return torch.where(estimate > 0, exact / torch.where(estimate > 0, estimate, 1.0), 1.0)


def analytic_ratio(
    light: Light, points: torch.Tensor, normals: torch.Tensor, estimate: torch.Tensor
) -> torch.Tensor | None:
    """(N,) G / estimate per receiver, the ratio estimator's factor on the diffuse term (module doc).

    Args:
        light: the light the samples were drawn from.
        points, normals: (N, 3) receivers and their normals (the normal the samples' cosines used).
        estimate: (N,) the samples' unshadowed Monte Carlo estimate of G, sum_s cos+ / (pdf S)
            times `estimate_weights`.

    Returns:
        the factor, 1 where the estimate is 0 (no sample to carry visibility: plain Monte
        Carlo is kept); None when the light has no closed form.
    """
    exact = closed_form(light, points, normals)
    return None if exact is None else ratio_of(exact, estimate)
