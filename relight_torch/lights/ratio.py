"""The lights whose unshadowed irradiance has a closed form, and the ratio estimator built on it.

Ratio estimator (Heitz, Hill & McGuire 2018, "Combining analytic direct illumination and
stochastic shadows"): with fixed light samples, the diffuse term sum_s f L V cos / (pdf S) is
multiplied per receiver by G / G_hat, G the closed-form cosine-weighted solid angle of the light
and G_hat the same samples' unshadowed estimate sum_s cos / (pdf S) of it. Exact where the light
is wholly visible or wholly hidden; noise only in penumbrae. Per-sample multipliers applied
afterwards (ShapingAPI, Barzel) keep it consistent: the result tends to the integral of the
shaped emission as samples grow.

Lights with a closed form: untextured RectLights (Lambert's polygon formula, `polygon`) and
SphereLights of positive radius (the projected solid angle of the visible cap, `sphere_cap`).
`normalize` scales L only, so it leaves G / G_hat unchanged. Every user of the closed form (the
direct relighter, the indirect methods' light on their samples, the multiview caching samples)
comes through `closed_form` here; the reference path tracer keeps sampling the same lights, and
tests hold the two to each other.
"""

from __future__ import annotations

import torch

from relight_torch.lights.light import Light, LightKind
from relight_torch.lights.polygon import has_rect_closed_form, rect_cosine_integral
from relight_torch.lights.sphere_cap import has_sphere_closed_form, sphere_cosine_integral


def has_closed_form(light: Light) -> bool:
    """Whether `closed_form` gives the light's unshadowed irradiance per unit radiance."""
    return has_rect_closed_form(light) or has_sphere_closed_form(light)


def closed_form(light: Light, points: torch.Tensor, normals: torch.Tensor) -> torch.Tensor | None:
    """G (N,) of the light at receivers (N, 3) with normals (N, 3); None without a closed form."""
    if not has_closed_form(light):
        return None
    if light.kind is LightKind.SPHERE:
        return sphere_cosine_integral(light, points, normals)
    return rect_cosine_integral(light, points, normals)


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
        estimate: (N,) the samples' unshadowed Monte Carlo estimate of G, sum_s cos+ / (pdf S) over
            samples reaching the emitting side.

    Returns:
        the factor, 1 where the estimate is 0 (no sample to carry visibility: plain Monte
        Carlo is kept); None when the light has no closed form.
    """
    exact = closed_form(light, points, normals)
    return None if exact is None else ratio_of(exact, estimate)
