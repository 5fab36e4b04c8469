"""Minnaert's (1941) limb-darkening reflectance, normalised:

    f = albedo (k + 1)/(2 pi) (cos_i cos_o)^(k - 1).

k = 1 is Lambert; k > 1 darkens towards grazing (lunar / dusty look); k < 1 brightens the rim
(the velvet look). Reciprocal. The directional albedo is albedo cos_o^(k - 1) in closed form:
<= albedo for k >= 1, but it grows without bound at grazing wo for k < 1, so the velvet range
does NOT conserve energy. Importance sampled exactly in wi by the cos^k density.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from relight_torch.brdf.common import check_pair, check_sample_args, expand_to, positive, where_above
from relight_torch.brdf.params import BrdfParams, colour, scalar
from relight_torch.math.sampling import power_cosine_hemisphere, power_cosine_pdf


@dataclass(frozen=True)
class MinnaertParams(BrdfParams):
    """albedo: (N, 3) reflectance at normal incidence; k: (N,) Minnaert exponent > -1."""

    albedo: torch.Tensor = colour()
    k: torch.Tensor = scalar()


def eval(params: MinnaertParams, wo_local: torch.Tensor, wi_local: torch.Tensor) -> torch.Tensor:
    """BRDF value (..., 3) in 1/sr for directions (..., 3); 0 below the horizon."""
    check_pair(wo_local, wi_local)
    cosines = positive(wo_local[..., 2]) * positive(wi_local[..., 2])
    lobe = (params.k + 1.0) / (2.0 * math.pi) * cosines ** (params.k - 1.0)
    return where_above(params.albedo * lobe.unsqueeze(-1), wo_local, wi_local)


def sample(params: MinnaertParams, wo_local: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """wi (..., 3) with density (k + 1)/(2 pi) cos^k(theta_i), and that pdf (...)."""
    check_sample_args(wo_local, u)
    wi_local, _ = power_cosine_hemisphere(u, params.k)
    wi_local = expand_to(wi_local, wo_local)
    return wi_local, pdf(params, wo_local, wi_local)


def pdf(params: MinnaertParams, wo_local: torch.Tensor, wi_local: torch.Tensor) -> torch.Tensor:
    """Solid-angle density (...) of `sample`; 0 where either direction is below the horizon."""
    check_pair(wo_local, wi_local)
    return where_above(power_cosine_pdf(wi_local[..., 2], params.k), wo_local, wi_local)
