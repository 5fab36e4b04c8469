"""Warps, their densities, Sobol points and hemisphere quadrature (relight_torch.math.sampling)."""

from __future__ import annotations

import math

import pytest
import torch

from relight_torch.math import sampling


def _uniform(num_points: int, device, dtype=torch.float64, seed=3) -> torch.Tensor:
    return torch.rand(num_points, 2, generator=torch.Generator().manual_seed(seed), dtype=dtype).to(device)


def test_concentric_disk_is_area_preserving(device):
    points, pdf = sampling.concentric_disk(_uniform(1 << 16, device))
    radius2 = (points * points).sum(-1)
    assert torch.all(radius2 <= 1.0 + 1e-12)
    assert torch.allclose(pdf, torch.full_like(pdf, 1 / math.pi))
    # Uniform in area: r^2 is uniform on [0, 1), and so is the angle; compare 8-bin histograms.
    num_points = radius2.numel()
    expected = num_points / 8
    sigma = math.sqrt(expected * (1 - 1 / 8))
    ring_counts = torch.bincount((radius2 * 8).long().clamp_max(7), minlength=8)
    angle = torch.atan2(points[:, 1], points[:, 0]) % (2 * math.pi)
    sector_counts = torch.bincount((angle / (2 * math.pi) * 8).long().clamp_max(7), minlength=8)
    assert torch.all((ring_counts - expected).abs() < 4 * sigma)
    assert torch.all((sector_counts - expected).abs() < 4 * sigma)


def test_concentric_disk_centre():
    points, _ = sampling.concentric_disk(torch.tensor([[0.5, 0.5]]))
    assert points.tolist() == [[0.0, 0.0]]


@pytest.mark.parametrize(
    "warp, pdf_of, target_integral",
    [
        (sampling.cosine_hemisphere, sampling.cosine_hemisphere_pdf, 1.0),
        (sampling.uniform_hemisphere, sampling.uniform_hemisphere_pdf, 1.0),
    ],
)
def test_hemisphere_warps_return_their_density(device, tolerances, warp, pdf_of, target_integral):
    directions, pdf = warp(_uniform(4096, device))
    torch.testing.assert_close(directions.norm(dim=-1), torch.ones_like(pdf), **tolerances[torch.float64])
    assert torch.all(directions[:, 2] >= 0)
    torch.testing.assert_close(pdf, pdf_of(directions), **tolerances[torch.float64])
    grid, weights = sampling.hemisphere_quadrature(256, 64, device=device, dtype=torch.float64)
    assert abs(float((pdf_of(grid) * weights).sum()) - target_integral) < 1e-4


def test_cosine_hemisphere_mean_cosine(device):
    # E[cos] under cos/pi is 2/3; the variance of cos is 1/2 - 4/9 = 1/18.
    directions, _ = sampling.cosine_hemisphere(_uniform(1 << 16, device))
    standard_error = math.sqrt(1 / 18 / directions.shape[0])
    assert abs(float(directions[:, 2].mean()) - 2 / 3) < 4 * standard_error


@pytest.mark.parametrize("exponent", [0.0, 1.0, 7.5, 60.0])
def test_power_cosine_density(device, tolerances, exponent):
    exponent_t = torch.tensor(exponent, dtype=torch.float64, device=device)
    directions, pdf = sampling.power_cosine_hemisphere(_uniform(4096, device), exponent_t)
    expected = sampling.power_cosine_pdf(directions[:, 2], exponent_t)
    torch.testing.assert_close(pdf, expected, **tolerances[torch.float64])
    grid, weights = sampling.hemisphere_quadrature(2048, 4, device=device, dtype=torch.float64)
    assert abs(float((sampling.power_cosine_pdf(grid[:, 2], exponent_t) * weights).sum()) - 1.0) < 1e-4
    # E[cos] = (e + 1)/(e + 2) in closed form.
    directions, _ = sampling.power_cosine_hemisphere(_uniform(1 << 16, device, seed=4), exponent_t)
    cosine = directions[:, 2]
    standard_error = float(cosine.std()) / math.sqrt(cosine.numel())
    assert abs(float(cosine.mean()) - (exponent + 1) / (exponent + 2)) < 4 * standard_error


def test_uniform_sphere_and_cone(device, tolerances):
    u = _uniform(1 << 14, device)
    directions, pdf = sampling.uniform_sphere(u)
    torch.testing.assert_close(pdf, sampling.uniform_sphere_pdf(directions))
    # Uniform on the sphere: each coordinate has mean 0 and variance 1/3.
    standard_error = math.sqrt(1 / 3 / u.shape[0])
    assert torch.all(directions.mean(0).abs() < 4 * standard_error)
    cos_max = torch.tensor(math.cos(0.3), dtype=torch.float64, device=device)
    directions, pdf = sampling.uniform_cone(u, cos_max)
    assert torch.all(directions[:, 2] >= cos_max - 1e-12)
    torch.testing.assert_close(pdf, sampling.uniform_cone_pdf(directions, cos_max), **tolerances[torch.float64])
    torch.testing.assert_close(
        pdf[0], torch.tensor(1 / (2 * math.pi * (1 - math.cos(0.3))), dtype=torch.float64, device=device)
    )
    assert float(sampling.uniform_cone_pdf(torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), cos_max.cpu())) == 0.0


def test_sobol_is_seeded_scrambled_and_half_open(device):
    points = sampling.sobol(1024, 3, seed=7, device=device)
    assert points.shape == (1024, 3) and points.dtype == torch.float32 and points.device.type == device.type
    assert torch.all((points >= 0) & (points < 1))
    assert torch.equal(points, sampling.sobol(1024, 3, seed=7, device=device))
    assert not torch.equal(points, sampling.sobol(1024, 3, seed=8, device=device))
    # A (0, m, s)-net property of Sobol: each of the 1024 1-D cells [k/1024, (k+1)/1024) holds one point.
    cells = (points.double() * 1024).long()
    for axis in range(3):
        assert torch.equal(torch.bincount(cells[:, axis], minlength=1024).cpu(), torch.ones(1024, dtype=torch.long))
    assert sampling.sobol(4, 2, dtype=torch.float64).dtype == torch.float64


def test_hemisphere_quadrature_integrates_cosine(device):
    directions, weights = sampling.hemisphere_quadrature(128, 32, device=device, dtype=torch.float64)
    assert abs(float(weights.sum()) - 2 * math.pi) < 1e-4
    assert abs(float((directions[:, 2] * weights).sum()) - math.pi) < 1e-4
