"""Cook-Torrance microfacet reflection with the GGX distribution (not Beckmann):

    f = F(wo . h) D(h) G(wo, wi) / (4 cos_o cos_i)

D: exact GGX of width alpha; G: separable Smith for GGX, G1(wo) G1(wi); F: Schlick with
F0 = f0 and F90 = 1. GGX rather than the paper's Beckmann so that the relighter, the bakers and
the UsdPreviewSurface lobe share one distribution and one sampler. Reciprocal (wo.h = wi.h).
Importance sampled with GGX visible normals (Heitz 2018); reflections below the horizon are
lost (pdf 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from relight_torch.brdf.common import check_pair, check_sample_args, positive, where_above
from relight_torch.brdf.params import BrdfParams, colour, scalar
from relight_torch.math.microfacet import (
    ggx_d,
    ggx_reflection_pdf,
    half_cosines,
    sample_ggx_reflection,
    schlick_fresnel,
    smith_g_ggx,
)


@dataclass(frozen=True)
class CookTorranceParams(BrdfParams):
    """f0: (N, 3) reflectance at normal incidence; alpha: (N,) GGX width (roughness^2) > 0."""

    f0: torch.Tensor = colour()
    alpha: torch.Tensor = scalar()


def eval(params: CookTorranceParams, wo_local: torch.Tensor, wi_local: torch.Tensor) -> torch.Tensor:
    """BRDF value (..., 3) in 1/sr for directions (..., 3); 0 below the horizon."""
    check_pair(wo_local, wi_local)
    cos_o, cos_i = wo_local[..., 2], wi_local[..., 2]
    cos_h, wo_dot_h = half_cosines(wo_local, wi_local)  # N.h as its pdf computes it
    fresnel = schlick_fresnel(params.f0, torch.ones_like(params.f0), wo_dot_h.unsqueeze(-1))
    microfacet = ggx_d(cos_h, params.alpha) * smith_g_ggx(cos_o, cos_i, params.alpha)
    value = fresnel * (microfacet / (4.0 * positive(cos_o) * positive(cos_i))).unsqueeze(-1)
    return where_above(value, wo_local, wi_local)


def sample(params: CookTorranceParams, wo_local: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """wi (..., 3) reflected about a GGX visible normal, with its pdf (...)."""
    check_sample_args(wo_local, u)
    return sample_ggx_reflection(wo_local, params.alpha, u)


def pdf(params: CookTorranceParams, wo_local: torch.Tensor, wi_local: torch.Tensor) -> torch.Tensor:
    """Solid-angle density (...) of `sample`: G1(wo) D(h) / (4 cos_o); 0 below the horizon."""
    check_pair(wo_local, wi_local)
    return ggx_reflection_pdf(wo_local, wi_local, params.alpha)
