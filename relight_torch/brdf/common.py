"""Helpers every BRDF module shares: argument checks, the horizon rule, lost samples."""

from __future__ import annotations

import torch

from relight_torch.math.checks import check_last_dim
from relight_torch.math.sampling import cosine_hemisphere, cosine_hemisphere_pdf


def check_pair(wo_local: torch.Tensor, wi_local: torch.Tensor) -> None:
    """Raise ValueError unless both directions are (..., 3) tensors."""
    check_last_dim(wo_local, 3, "wo_local")
    check_last_dim(wi_local, 3, "wi_local")


def check_sample_args(wo_local: torch.Tensor, u: torch.Tensor) -> None:
    """Raise ValueError unless wo is (..., 3) and the random numbers u are (..., 2)."""
    check_last_dim(wo_local, 3, "wo_local")
    check_last_dim(u, 2, "u")


def above_horizon(wo_local: torch.Tensor, wi_local: torch.Tensor) -> torch.Tensor:
    """(...) bool: both directions strictly above the surface (z > 0), where a BRDF may be non-zero."""
    return (wo_local[..., 2] > 0) & (wi_local[..., 2] > 0)


def where_above(value: torch.Tensor, wo_local: torch.Tensor, wi_local: torch.Tensor) -> torch.Tensor:
    """`value` (..., 3) or (...) where both directions are above the horizon, else 0."""
    valid = above_horizon(wo_local, wi_local)
    if value.dim() == valid.dim() + 1:
        valid = valid.unsqueeze(-1)
    return torch.where(valid, value, 0.0)


def positive(cos_theta: torch.Tensor) -> torch.Tensor:
    """A cosine clamped away from 0, safe to divide by in branches that `where_above` discards."""
    return cos_theta.clamp_min(torch.finfo(cos_theta.dtype).tiny)


def mirror(wo_local: torch.Tensor) -> torch.Tensor:
    """Mirror direction of wo about the local normal, (-x, -y, z), (..., 3)."""
    return wo_local * torch.tensor([-1.0, -1.0, 1.0], device=wo_local.device, dtype=wo_local.dtype)


def expand_to(tensor: torch.Tensor, *others: torch.Tensor) -> torch.Tensor:
    """Broadcast a (..., 3) direction to the batch shape it shares with `others` (..., k)."""
    shapes = (tensor.shape[:-1], *(o.shape[:-1] for o in others))
    batch = torch.broadcast_shapes(*shapes)  # type: ignore[no-untyped-call]  # unannotated in torch
    return tensor.expand(*batch, tensor.shape[-1])


def sample_cosine(wo_local: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Cosine-distributed wi (..., 3) from u (..., 2) and its pdf `cosine_pdf` (...)."""
    check_sample_args(wo_local, u)
    wi_local, _ = cosine_hemisphere(u)
    wi_local = expand_to(wi_local, wo_local)
    return wi_local, cosine_pdf(wo_local, wi_local)


def cosine_pdf(wo_local: torch.Tensor, wi_local: torch.Tensor) -> torch.Tensor:
    """cos(theta_i)/pi (...) where both directions are above the horizon, else 0."""
    check_pair(wo_local, wi_local)
    return where_above(cosine_hemisphere_pdf(wi_local), wo_local, wi_local)
