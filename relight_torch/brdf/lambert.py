"""Lambertian diffuse reflection, f = albedo / pi; importance sampled by the cosine.

Reciprocal; directional albedo exactly `albedo` for every wo above the horizon.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from relight_torch.brdf.common import check_pair, cosine_pdf, sample_cosine, where_above
from relight_torch.brdf.params import BrdfParams, colour


@dataclass(frozen=True)
class LambertParams(BrdfParams):
    """albedo: (N, 3) diffuse reflectance in [0, 1]."""

    albedo: torch.Tensor = colour()


def eval(params: LambertParams, wo_local: torch.Tensor, wi_local: torch.Tensor) -> torch.Tensor:
    """BRDF value (..., 3) in 1/sr for directions (..., 3); 0 below the horizon."""
    check_pair(wo_local, wi_local)
    return where_above(params.albedo / math.pi * torch.ones_like(wi_local), wo_local, wi_local)


def sample(params: LambertParams, wo_local: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Cosine-distributed wi (..., 3) from u (..., 2), with its pdf (...) (0 if wo is below)."""
    return sample_cosine(wo_local, u)


def pdf(params: LambertParams, wo_local: torch.Tensor, wi_local: torch.Tensor) -> torch.Tensor:
    """Solid-angle density (...) of `sample`: cos(theta_i)/pi where both are above the horizon."""
    return cosine_pdf(wo_local, wi_local)
