"""Microfacet building blocks as free functions: GGX distributions, Smith masking, Schlick
Fresnel, and GGX visible-normal sampling.

Two GGX normal distributions live here on purpose:

* `ggx_d`: the exact, normalised GGX / Trowbridge-Reitz NDF (integral of D cos_h = 1), used by
  Cook-Torrance and by every sampling pdf.
* `storm_ggx_d`: the variant in Storm's `previewSurface.glslfx`, whose numerator carries an extra
  EPSILON = 0.001: (a^2 + 0.001) / (pi ((n.h)^2 (a^2 - 1) + 1)^2). It is NOT normalised: it scales
  the lobe by (a^2 + 0.001) / a^2, i.e. it adds energy at low roughness (x11 at roughness 0.1).
  Used only by the UsdPreviewSurface BRDF, to match Storm.

`alpha` is the GGX width (UsdPreviewSurface: alpha = roughness^2). All arguments broadcast
against each other; cosines are clamped to [0, 1] as Storm does.
"""

from __future__ import annotations

import math

import torch

from relight_torch.math.frame import dot, reflect

STORM_EPSILON = 0.001
"""The EPSILON of previewSurface.glslfx, in the NDF numerator and the specular denominator."""


def _ggx_denominator(cos_h: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    # (n.h)^2 (a^2 - 1) + 1 rewritten as sin^2 + a^2 cos^2: the same value, but it does not
    # cancel to 0 in float32 when a^2 < 1e-7 (roughness 0.001 gives a^2 = 1e-12).
    cos_h = cos_h.clamp(0.0, 1.0)
    sin2_h = (1.0 - cos_h) * (1.0 + cos_h)
    return math.pi * (sin2_h + alpha * alpha * cos_h * cos_h) ** 2


def ggx_d(cos_h: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Exact GGX NDF D(h) = a^2 / (pi ((n.h)^2 (a^2 - 1) + 1)^2), in 1/sr.

    Args:
        cos_h: (...) cosine between the microfacet normal and the shading normal.
        alpha: (...) GGX width, > 0.
    """
    return alpha * alpha / _ggx_denominator(cos_h, alpha)


def storm_ggx_d(cos_h: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Storm's previewSurface NDF (a^2 + 0.001) / (pi ((n.h)^2 (a^2 - 1) + 1)^2), not normalised.

    Args:
        cos_h: (...) cosine between the half vector and the shading normal.
        alpha: (...) GGX width = max(roughness, 0.001)^2.
    """
    return (alpha * alpha + STORM_EPSILON) / _ggx_denominator(cos_h, alpha)


def smith_g1_ggx(cos_theta: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Exact Smith masking for GGX, G1 = 2 cos / (cos + sqrt(a^2 + (1 - a^2) cos^2)).

    Args:
        cos_theta: (...) cosine of the direction with the shading normal (clamped to [0, 1]).
        alpha: (...) GGX width, > 0.
    """
    cos_theta = cos_theta.clamp(0.0, 1.0)
    alpha2 = alpha * alpha
    root = torch.sqrt(alpha2 + (1.0 - alpha2) * cos_theta * cos_theta)
    return 2.0 * cos_theta / (cos_theta + root).clamp_min(torch.finfo(cos_theta.dtype).tiny)


def smith_g_ggx(cos_o: torch.Tensor, cos_i: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Separable Smith shadowing-masking for GGX, G1(wo) G1(wi). Shapes broadcast, (...)."""
    return smith_g1_ggx(cos_o, alpha) * smith_g1_ggx(cos_i, alpha)


def schlick_ggx_g1(cos_theta: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """Schlick's approximation of Smith masking, cos / (cos (1 - k) + k). Shapes broadcast."""
    cos_theta = cos_theta.clamp(0.0, 1.0)
    return cos_theta / (cos_theta * (1.0 - k) + k)


def storm_schlick_ggx_g(cos_o: torch.Tensor, cos_i: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Storm's `Geometric`: Schlick-GGX masking with k = alpha / 2 for both directions.

    Args:
        cos_o, cos_i: (...) NdotE and NdotL.
        alpha: (...) GGX width = max(roughness, 0.001)^2.
    """
    k = 0.5 * alpha
    return schlick_ggx_g1(cos_o, k) * schlick_ggx_g1(cos_i, k)


def schlick_fresnel(f0: torch.Tensor, f90: torch.Tensor | float, cos_theta: torch.Tensor) -> torch.Tensor:
    """Schlick Fresnel, mix(f0, f90, (1 - cos)^5), with cos clamped to [0, 1].

    All arguments broadcast; to weight a colour (..., 3) by a cosine (...), pass cos[..., None].
    """
    weight = (1.0 - cos_theta.clamp(0.0, 1.0)) ** 5
    return f0 + (f90 - f0) * weight


def sample_ggx_visible_normal(wo_local: torch.Tensor, alpha: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Draw a microfacet normal from the GGX distribution of normals visible from `wo`.

    Heitz 2018, "Sampling the GGX Distribution of Visible Normals" (JCGT 7(4)), isotropic.
    The density of the result is `ggx_visible_normal_pdf`.

    Args:
        wo_local: (..., 3) unit direction with wo.z > 0.
        alpha: (...) GGX width, > 0.
        u: (..., 2) uniform numbers in [0, 1).

    Returns:
        (..., 3) unit microfacet normal in the local frame, h.z >= 0.
    """
    alpha = alpha[..., None]
    # Stretch the view so that the GGX becomes the hemisphere of a unit sphere.
    stretched = torch.nn.functional.normalize(
        torch.cat((alpha * wo_local[..., :2], wo_local[..., 2:3]), dim=-1), dim=-1, eps=1e-12
    )
    vx, vy, vz = stretched.unbind(-1)
    length2 = vx * vx + vy * vy
    inv_length = torch.rsqrt(length2.clamp_min(torch.finfo(length2.dtype).tiny))
    has_azimuth = length2 > 0
    t1 = torch.stack(
        (
            torch.where(has_azimuth, -vy * inv_length, torch.ones_like(vx)),
            torch.where(has_azimuth, vx * inv_length, torch.zeros_like(vx)),
            torch.zeros_like(vx),
        ),
        dim=-1,
    )
    t2 = torch.linalg.cross(stretched, t1, dim=-1)
    # Uniform point on the projected disk, squeezed onto the visible half.
    radius = torch.sqrt(u[..., 0])
    phi = 2.0 * math.pi * u[..., 1]
    p1 = radius * torch.cos(phi)
    p2 = radius * torch.sin(phi)
    s = 0.5 * (1.0 + vz)
    p2 = (1.0 - s) * torch.sqrt((1.0 - p1 * p1).clamp_min(0.0)) + s * p2
    p3 = torch.sqrt((1.0 - p1 * p1 - p2 * p2).clamp_min(0.0))
    normal_stretched = p1.unsqueeze(-1) * t1 + p2.unsqueeze(-1) * t2 + p3.unsqueeze(-1) * stretched
    # Unstretch back to the ellipsoid configuration.
    return torch.nn.functional.normalize(
        torch.cat((alpha * normal_stretched[..., :2], normal_stretched[..., 2:3].clamp_min(0.0)), dim=-1),
        dim=-1,
        eps=1e-12,
    )


def ggx_visible_normal_pdf(wo_local: torch.Tensor, h_local: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Solid-angle density of `sample_ggx_visible_normal`: G1(wo) max(0, wo.h) D(h) / wo.z.

    Args:
        wo_local: (..., 3) unit direction; density 0 where wo.z <= 0.
        h_local: (..., 3) unit microfacet normal.
        alpha: (...) GGX width.

    Returns:
        (...) density in 1/sr.
    """
    cos_o = wo_local[..., 2]
    wo_dot_h = (wo_local * h_local).sum(-1).clamp_min(0.0)
    density = smith_g1_ggx(cos_o, alpha) * wo_dot_h * ggx_d(h_local[..., 2], alpha)
    return torch.where(cos_o > 0, density / cos_o.clamp_min(torch.finfo(cos_o.dtype).tiny), 0.0)


def sample_ggx_reflection(
    wo_local: torch.Tensor, alpha: torch.Tensor, u: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Reflect `wo` about a GGX visible normal.

    Args:
        wo_local: (..., 3) unit direction.
        alpha: (...) GGX width.
        u: (..., 2) uniform numbers in [0, 1).

    Returns:
        wi_local (..., 3) and its solid-angle pdf (...), equal to `ggx_reflection_pdf(wo, wi)`;
        the pdf is 0 for a lost sample (wo or wi below the horizon).
    """
    h_local = sample_ggx_visible_normal(wo_local, alpha, u)
    wi_local = reflect(wo_local, h_local)
    return wi_local, ggx_reflection_pdf(wo_local, wi_local, alpha)


def half_cosines(wo_local: torch.Tensor, wi_local: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N.h, wo.h), each (...), of the half vector h = (wo + wi) / max(|wo + wi|, 1e-12).

    The one computation of N.h for microfacet values and for their densities. Below roughness
    ~0.03 (a^2 < 1e-6) D changes by orders of magnitude between neighbouring float32 values of N.h
    near 1 (1 - N.h is resolved to 6e-8, sin^2 to 1.2e-7), so a value and its pdf computed by two
    formulas for h (a division by the norm and F.normalize differ by an ulp) gave weights f cos / pdf
    of several hundred at roughness 0.01; from one formula their D cancel exactly.

    Args:
        wo_local, wi_local: (..., 3) unit directions.
    """
    h = wo_local + wi_local
    length = dot(h, h).sqrt().clamp_min(1e-12)
    return h[..., 2] / length, dot(wo_local, h) / length


def ggx_reflection_pdf(wo_local: torch.Tensor, wi_local: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Density of `sample_ggx_reflection` in solid angle of wi: G1(wo) D(h) / (4 wo.z).

    The Jacobian of the reflection, 1 / (4 wo.h), cancels the wo.h of the visible-normal pdf.

    Args:
        wo_local, wi_local: (..., 3) unit directions; density 0 unless both are above the horizon.
        alpha: (...) GGX width.

    Returns:
        (...) density in 1/sr.
    """
    cos_o, cos_i = wo_local[..., 2], wi_local[..., 2]
    density = smith_g1_ggx(cos_o, alpha) * ggx_d(half_cosines(wo_local, wi_local)[0], alpha)
    valid = (cos_o > 0) & (cos_i > 0)
    return torch.where(valid, density / (4.0 * cos_o.clamp_min(torch.finfo(cos_o.dtype).tiny)), 0.0)
