"""Oren-Nayar rough diffuse reflection, the qualitative model of Oren & Nayar 1994 (eq. 30):

    f = albedo/pi (A + B max(0, cos(phi_i - phi_o)) sin(alpha) tan(beta)),
    A = 1 - 0.5 s^2/(s^2 + 0.33),  B = 0.45 s^2/(s^2 + 0.09),  s = sigma (radians),
    alpha = max(theta_i, theta_o), beta = min(theta_i, theta_o).

The angular factor equals max(0, wi_xy . wo_xy) / max(cos_i, cos_o), the form evaluated here.
Reciprocal; sigma = 0 is Lambert. Importance sampled by the cosine.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from relight_torch.brdf.common import check_pair, cosine_pdf, sample_cosine, where_above
from relight_torch.brdf.params import BrdfParams, colour, scalar


@dataclass(frozen=True)
class OrenNayarParams(BrdfParams):
    """albedo: (N, 3) reflectance; sigma: (N,) standard deviation of facet slopes, radians."""

    albedo: torch.Tensor = colour()
    sigma: torch.Tensor = scalar()


def eval(params: OrenNayarParams, wo_local: torch.Tensor, wi_local: torch.Tensor) -> torch.Tensor:
    """BRDF value (..., 3) in 1/sr for directions (..., 3); 0 below the horizon."""
    check_pair(wo_local, wi_local)
    sigma2 = params.sigma * params.sigma
    a = 1.0 - 0.5 * sigma2 / (sigma2 + 0.33)
    b = 0.45 * sigma2 / (sigma2 + 0.09)
    azimuthal = (wo_local[..., :2] * wi_local[..., :2]).sum(-1).clamp_min(0.0)
    larger_cos = torch.maximum(wo_local[..., 2], wi_local[..., 2]).clamp_min(torch.finfo(wo_local.dtype).tiny)
    angular = a + b * azimuthal / larger_cos
    return where_above(params.albedo / math.pi * angular.unsqueeze(-1), wo_local, wi_local)


def sample(params: OrenNayarParams, wo_local: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Cosine-distributed wi (..., 3) from u (..., 2), with its pdf (...) (0 if wo is below)."""
    return sample_cosine(wo_local, u)


def pdf(params: OrenNayarParams, wo_local: torch.Tensor, wi_local: torch.Tensor) -> torch.Tensor:
    """Solid-angle density (...) of `sample`: cos(theta_i)/pi where both are above the horizon."""
    return cosine_pdf(wo_local, wi_local)
