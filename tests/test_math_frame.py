"""Orthonormal bases and frame changes (relight_torch.math.frame)."""

from __future__ import annotations

import math

import torch

from relight_torch.math.frame import half_vector, orthonormal_basis, reflect, to_local, to_world


def _normals(device, dtype) -> torch.Tensor:
    generator = torch.Generator().manual_seed(1)
    random = torch.nn.functional.normalize(torch.randn(1000, 3, generator=generator, dtype=torch.float64), dim=-1)
    # The poles and the neighbourhood of -z are where naive constructions break down.
    special = torch.tensor(
        [[0, 0, 1], [0, 0, -1], [1e-7, 0, -1], [0, 1e-4, -1], [1, 0, 0], [0, -1, 0]], dtype=torch.float64
    )
    special = torch.nn.functional.normalize(special, dim=-1)
    return torch.cat((random, special)).to(device=device, dtype=dtype)


def test_basis_is_orthonormal_and_right_handed(device, tolerances):
    for dtype in (torch.float32, torch.float64):
        normal = _normals(device, dtype)
        tangent, bitangent = orthonormal_basis(normal)
        frame = torch.stack((tangent, bitangent, normal), dim=-2)
        identity = torch.eye(3, device=device, dtype=dtype).expand_as(frame)
        atol = 10 * torch.finfo(dtype).eps
        torch.testing.assert_close(frame @ frame.transpose(-1, -2), identity, rtol=0, atol=atol)
        torch.testing.assert_close(torch.linalg.cross(tangent, bitangent, dim=-1), normal, rtol=0, atol=atol)


def test_basis_of_z_is_the_identity_frame(device):
    tangent, bitangent = orthonormal_basis(torch.tensor([0.0, 0.0, 1.0], device=device))
    assert tangent.tolist() == [1.0, 0.0, 0.0]
    assert bitangent.tolist() == [0.0, 1.0, 0.0]


def test_local_world_round_trip(device, tolerances):
    dtype = torch.float64
    normal = _normals(device, dtype)
    tangent, bitangent = orthonormal_basis(normal)
    v_world = torch.randn(normal.shape, generator=torch.Generator().manual_seed(2), dtype=dtype).to(device)
    v_local = to_local(v_world, tangent, bitangent, normal)
    torch.testing.assert_close(to_world(v_local, tangent, bitangent, normal), v_world, **tolerances[dtype])
    # The normal itself is +z locally.
    torch.testing.assert_close(
        to_local(normal, tangent, bitangent, normal),
        torch.tensor([0.0, 0.0, 1.0], device=device, dtype=dtype).expand_as(normal),
        **tolerances[dtype],
    )


def test_reflect_and_half_vector(device, tolerances):
    dtype = torch.float64
    wo = torch.tensor([math.sin(0.5), 0.0, math.cos(0.5)], device=device, dtype=dtype)
    normal = torch.tensor([0.0, 0.0, 1.0], device=device, dtype=dtype)
    wi = reflect(wo, normal)
    torch.testing.assert_close(wi, torch.tensor([-math.sin(0.5), 0.0, math.cos(0.5)], dtype=dtype, device=device))
    torch.testing.assert_close(half_vector(wo, wi), normal, **tolerances[dtype])
    assert torch.all(half_vector(wo, -wo) == 0)
