"""The closed-form irradiance of a SphereLight (lights/sphere_cap.py) against hand values, a
deterministic quadrature over the cap, and Monte Carlo through `sample_light` (the sampler the
reference path tracer uses for the same light)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from relight_torch.lights.light import Light, LightKind
from relight_torch.lights.ratio import analytic_ratio, closed_form, has_closed_form
from relight_torch.lights.sphere_cap import sphere_cosine_integral
from test_lights_polygon import monte_carlo


def sphere(centre, radius: float, scale: float = 1.0) -> Light:
    matrix = np.eye(4)
    matrix[:3, :3] *= scale
    matrix[:3, 3] = centre
    return Light("/S", LightKind.SPHERE, radius=radius, world_from_light=matrix)


def quadrature(alpha: float, theta: float, steps: int = 3000) -> float:
    """G of a cap of half-angle alpha whose axis makes angle theta with the normal, by the midpoint
    rule over (cos of the angle from the axis, azimuth): uniform in solid angle."""
    cos_alpha = math.cos(alpha)
    mu = cos_alpha + (1.0 - cos_alpha) * (torch.arange(steps, dtype=torch.float64) + 0.5) / steps
    phi = 2.0 * math.pi * (torch.arange(steps, dtype=torch.float64) + 0.5) / steps
    mu, phi = mu.unsqueeze(1), phi.unsqueeze(0)
    sin_mu = (1.0 - mu.square()).sqrt()
    # The axis in the (x, z) plane at angle theta from the normal +z; omega around it.
    cosine = mu * math.cos(theta) + sin_mu * torch.cos(phi) * math.sin(theta)
    return float(cosine.clamp_min(0.0).mean()) * 2.0 * math.pi * (1.0 - cos_alpha)


def test_a_cap_above_the_horizon_is_pi_sin2_alpha_cos_theta():
    light = sphere((0.0, 0.0, 2.0), 0.5)
    points = torch.zeros(3, 3, dtype=torch.float64)
    theta = [0.0, 0.7, math.pi / 2 - math.asin(0.25) - 1e-9]  # the last just touches the horizon
    normals = torch.tensor([[math.sin(t), 0.0, math.cos(t)] for t in theta], dtype=torch.float64)
    expected = [math.pi * 0.25**2 * math.cos(t) for t in theta]
    assert sphere_cosine_integral(light, points, normals).tolist() == pytest.approx(expected, rel=1e-12)
    # Facing away, and from inside the sphere: nothing.
    away = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
    assert float(sphere_cosine_integral(light, points[:1], away)) == 0.0
    inside = torch.tensor([[0.0, 0.0, 1.8]], dtype=torch.float64)
    assert float(sphere_cosine_integral(light, inside, away)) == 0.0


@pytest.mark.parametrize(
    ("alpha", "theta"), [(0.3, math.pi / 2), (0.3, math.pi / 2 + 0.2), (0.3, 1.4), (1.2, 2.0), (0.02, 1.575)]
)
def test_caps_cut_by_the_horizon_match_quadrature(alpha, theta):
    distance = 3.0
    light = sphere((0.0, 0.0, distance), distance * math.sin(alpha))
    normal = torch.tensor([[math.sin(theta), 0.0, math.cos(theta)]], dtype=torch.float64)
    value = float(sphere_cosine_integral(light, torch.zeros(1, 3, dtype=torch.float64), normal))
    expected = quadrature(alpha, theta)
    assert expected > 0.0 and value == pytest.approx(expected, rel=2e-5)


@pytest.mark.parametrize(("radius", "scale"), [(0.6, 1.0), (0.3, 1.7)])
def test_random_receivers_match_monte_carlo_of_the_reference_sampler(radius, scale):
    light = sphere((0.2, 0.1, 1.0), radius, scale)
    generator = torch.Generator().manual_seed(11)
    points = (torch.rand(64, 3, generator=generator, dtype=torch.float64) - 0.5) * 3.0
    # Normals of lengths 0.9-1.1: G is homogeneous of degree 1 in the normal.
    normals = torch.nn.functional.normalize(torch.randn(64, 3, generator=generator, dtype=torch.float64), dim=-1)
    normals = normals * (0.9 + 0.2 * torch.rand(64, 1, generator=generator, dtype=torch.float64))
    exact = sphere_cosine_integral(light, points, normals)
    mean, error = monte_carlo(light, points, normals, 40000)
    assert (exact - mean).abs().max() <= (4.5 * error).max() + 1e-12
    # The draw holds every case: wholly above the horizon, cut by it, wholly below, inside.
    to_centre = torch.as_tensor(light.world_from_light[:3, 3]) - points
    distance = to_centre.norm(dim=-1)
    cos_theta = (to_centre * normals).sum(-1) / (distance * normals.norm(dim=-1))
    sin_alpha = radius * scale / distance
    assert int((cos_theta > sin_alpha).sum()) >= 10 and int((cos_theta < -sin_alpha).sum()) >= 10
    assert int((cos_theta.abs() < sin_alpha).sum()) >= 10 and int((distance < radius * scale).sum()) >= 1


def test_a_small_light_in_float32_matches_float64():
    light = sphere((0.0, 0.0, 4.0), 0.01)  # 2.5 milliradians
    generator = torch.Generator().manual_seed(2)
    angles = math.pi / 2 + (torch.rand(256, generator=generator, dtype=torch.float64) - 0.5) * 0.01
    normals = torch.stack((angles.sin(), torch.zeros_like(angles), angles.cos()), dim=-1)
    points = torch.zeros(256, 3, dtype=torch.float64)
    double = sphere_cosine_integral(light, points, normals)
    single = sphere_cosine_integral(light, points.float(), normals.float())
    assert int((double > 0).sum()) >= 100  # most are cut by the horizon
    torch.testing.assert_close(single.double(), double, rtol=1e-4, atol=1e-12)


def test_ratio_is_exact_for_any_unshadowed_samples_and_point_lights_have_no_closed_form():
    light = sphere((0.0, 0.0, 1.0), 0.3)
    points = torch.tensor([[0.1, 0.2, 0.0], [0.9, -0.3, 0.9]], dtype=torch.float64)
    normals = torch.tensor([[0.0, 0.0, 1.0], [-0.6, 0.0, 0.8]], dtype=torch.float64)
    few, _ = monte_carlo(light, points, normals, 2)
    assert has_closed_form(light)
    ratio = analytic_ratio(light, points, normals, few)
    torch.testing.assert_close(ratio * few, closed_form(light, points, normals), rtol=1e-12, atol=0.0)
    assert not has_closed_form(sphere((0.0, 0.0, 1.0), 0.0))
    assert closed_form(sphere((0.0, 0.0, 1.0), 0.0), points, normals) is None
