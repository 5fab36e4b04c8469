"""Normalised Blinn-Phong lobe:

    f = ks c(n) (n . h)^n,   c(n) = (n + 2)(n + 4) / (8 pi (2^(-n/2) + n)).

c(n) is the exact normalisation making the directional albedo equal to ks at normal incidence
(the integral of (n.h)^n cos(theta_i) over the hemisphere at wo = n is 8 pi (n + 2^(-n/2)) /
((n + 2)(n + 4))); the popular (n + 8)/(8 pi) only approximates it and overshoots (by 7 % at
n = 10). Reciprocal. Importance sampled by drawing h from the (n + 1)/(2 pi) cos^n density and
reflecting wo about it; reflections below the horizon are lost (pdf 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from relight_torch.brdf.common import check_pair, check_sample_args, positive, where_above
from relight_torch.brdf.params import BrdfParams, colour, scalar
from relight_torch.math.frame import half_vector, reflect
from relight_torch.math.sampling import power_cosine_hemisphere, power_cosine_pdf


@dataclass(frozen=True)
class BlinnPhongParams(BrdfParams):
    """ks: (N, 3) specular reflectance; exponent: (N,) Blinn-Phong exponent n >= 0."""

    ks: torch.Tensor = colour()
    exponent: torch.Tensor = scalar()


def normalization(exponent: torch.Tensor) -> torch.Tensor:
    """c(n) of the module docstring, (...) for exponents (...)."""
    return (exponent + 2.0) * (exponent + 4.0) / (8.0 * math.pi * (2.0 ** (-0.5 * exponent) + exponent))


def eval(params: BlinnPhongParams, wo_local: torch.Tensor, wi_local: torch.Tensor) -> torch.Tensor:
    """BRDF value (..., 3) in 1/sr for directions (..., 3); 0 below the horizon."""
    check_pair(wo_local, wi_local)
    cos_h = half_vector(wo_local, wi_local)[..., 2].clamp_min(0.0)
    lobe = normalization(params.exponent) * cos_h**params.exponent
    return where_above(params.ks * lobe.unsqueeze(-1), wo_local, wi_local)


def sample(params: BlinnPhongParams, wo_local: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """wi (..., 3): wo reflected about h ~ cos^n(theta_h), with its pdf (...)."""
    check_sample_args(wo_local, u)
    h_local, _ = power_cosine_hemisphere(u, params.exponent)
    wi_local = reflect(wo_local, h_local)
    return wi_local, pdf(params, wo_local, wi_local)


def pdf(params: BlinnPhongParams, wo_local: torch.Tensor, wi_local: torch.Tensor) -> torch.Tensor:
    """Solid-angle density (...) of `sample`: p(h) / (4 wo.h); 0 below the horizon."""
    check_pair(wo_local, wi_local)
    h_local = half_vector(wo_local, wi_local)
    wo_dot_h = (wo_local * h_local).sum(-1)
    density = power_cosine_pdf(h_local[..., 2], params.exponent) / (4.0 * positive(wo_dot_h))
    return where_above(density, wo_local, wi_local)
