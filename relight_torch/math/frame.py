"""Shading frames: orthonormal bases, changes of frame, reflection and half vectors.

Local shading frame convention (shared by every BRDF): x = tangent, y = bitangent, z = shading
normal, right-handed. Directions are unit vectors pointing AWAY from the surface.
"""

from __future__ import annotations

import torch


def orthonormal_basis(normal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Tangent and bitangent completing a unit normal into a right-handed frame.

    Branchless construction of Duff et al. 2017, "Building an Orthonormal Basis, Revisited"
    (JCGT 6(1)); continuous everywhere except across the plane n.z = 0 where the sign flips.

    Args:
        normal: (..., 3) unit vectors.

    Returns:
        (tangent, bitangent), each (..., 3) unit, with tangent x bitangent = normal.
    """
    x, y, z = normal.unbind(-1)
    sign = torch.copysign(torch.ones_like(z), z)
    a = -1.0 / (sign + z)
    b = x * y * a
    tangent = torch.stack((1.0 + sign * x * x * a, sign * b, -sign * x), dim=-1)
    bitangent = torch.stack((b, sign + y * y * a, -y), dim=-1)
    return tangent, bitangent


def dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Dot products (...) of broadcasting vectors (..., 3), summed by components in place.

    On the CPU a reduction over a last axis of 3, `(a * b).sum(-1)`, costs ~2.5x one product and
    two multiply-adds into it, and summing three product temporaries ~5x (150,000 vectors on one
    thread: 0.70 and 1.37 ms against 0.27 ms).
    """
    return (a[..., 0] * b[..., 0]).addcmul_(a[..., 1], b[..., 1]).addcmul_(a[..., 2], b[..., 2])


def length(v: torch.Tensor) -> torch.Tensor:
    """Euclidean lengths (...) of vectors (..., 3): `dot` and a square root in place, ~3x faster
    on the CPU than `norm(dim=-1)` (150,000 vectors on one thread: 0.6 against 1.7 ms)."""
    return dot(v, v).sqrt_()


def to_local(
    v_world: torch.Tensor, tangent: torch.Tensor, bitangent: torch.Tensor, normal: torch.Tensor
) -> torch.Tensor:
    """Express world vectors (..., 3) in the frame (tangent, bitangent, normal), each (..., 3)."""
    return torch.stack((dot(v_world, tangent), dot(v_world, bitangent), dot(v_world, normal)), dim=-1)


def to_world(
    v_local: torch.Tensor, tangent: torch.Tensor, bitangent: torch.Tensor, normal: torch.Tensor
) -> torch.Tensor:
    """Inverse of `to_local`: local (..., 3) coordinates back to world vectors (..., 3)."""
    return v_local[..., 0:1] * tangent + v_local[..., 1:2] * bitangent + v_local[..., 2:3] * normal


def reflect(w: torch.Tensor, axis: torch.Tensor) -> torch.Tensor:
    """Mirror direction of `w` (..., 3) about the unit `axis` (..., 3): 2 (w.axis) axis - w."""
    return 2.0 * (w * axis).sum(-1, keepdim=True) * axis - w


def half_vector(wo: torch.Tensor, wi: torch.Tensor) -> torch.Tensor:
    """Unit half vector normalize(wo + wi) of two unit directions (..., 3).

    Returns a zero vector (not NaN) for exactly opposite directions; callers mask those out.
    """
    return torch.nn.functional.normalize(wo + wi, dim=-1, eps=1e-12)
