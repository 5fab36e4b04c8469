"""Modified (energy-conserving) Phong lobe of Lafortune & Willems 1994:

    f = ks (n + 2)/(2 pi) max(0, wi . r)^n,   r = mirror direction of wo.

Reciprocal (wi . r(wo) = wo . r(wi)). The normalisation makes the directional albedo exactly ks
at normal incidence and less elsewhere (part of the lobe falls below the horizon), so ks <= 1
conserves energy. Importance sampled by the cos^n lobe around r; samples that fall below the
horizon are lost (pdf 0), so the pdf integrates to less than 1 away from normal incidence.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from relight_torch.brdf.common import check_pair, check_sample_args, expand_to, mirror, where_above
from relight_torch.brdf.params import BrdfParams, colour, scalar
from relight_torch.math.frame import orthonormal_basis, to_world
from relight_torch.math.sampling import power_cosine_hemisphere, power_cosine_pdf


@dataclass(frozen=True)
class PhongParams(BrdfParams):
    """ks: (N, 3) specular reflectance; exponent: (N,) Phong exponent n >= 0."""

    ks: torch.Tensor = colour()
    exponent: torch.Tensor = scalar()


def eval(params: PhongParams, wo_local: torch.Tensor, wi_local: torch.Tensor) -> torch.Tensor:
    """BRDF value (..., 3) in 1/sr for directions (..., 3); 0 below the horizon."""
    check_pair(wo_local, wi_local)
    cos_alpha = (wi_local * mirror(wo_local)).sum(-1).clamp_min(0.0)
    lobe = (params.exponent + 2.0) / (2.0 * math.pi) * cos_alpha**params.exponent
    return where_above(params.ks * lobe.unsqueeze(-1), wo_local, wi_local)


def sample(params: PhongParams, wo_local: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """wi (..., 3) from the cos^n lobe around the mirror direction, with its pdf (...)."""
    check_sample_args(wo_local, u)
    lobe_axis = expand_to(mirror(wo_local), u)
    wi_lobe, _ = power_cosine_hemisphere(u, params.exponent)
    tangent, bitangent = orthonormal_basis(lobe_axis)
    wi_local = to_world(wi_lobe, tangent, bitangent, lobe_axis)
    return wi_local, pdf(params, wo_local, wi_local)


def pdf(params: PhongParams, wo_local: torch.Tensor, wi_local: torch.Tensor) -> torch.Tensor:
    """Solid-angle density (...) of `sample`, 0 where either direction is below the horizon."""
    check_pair(wo_local, wi_local)
    cos_alpha = (wi_local * mirror(wo_local)).sum(-1)
    return where_above(power_cosine_pdf(cos_alpha, params.exponent), wo_local, wi_local)
