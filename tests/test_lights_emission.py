"""Light radiometry and sampling against hand-computed values and closed-form irradiances.

Monte Carlo checks use fixed seeds and a tolerance of 4.5 standard errors of the estimate itself.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from relight_torch.lights.emission import (
    emitted_radiance,
    intersect_light,
    light_pdf,
    light_radiance_scale,
    sample_light,
    size_factor,
    validate_light,
)
from relight_torch.lights.light import Light, LightKind
from relight_torch.math.frame import orthonormal_basis, to_world
from relight_torch.math.sampling import cosine_hemisphere, uniform_sphere

NUM_SIGMA = 4.5


def transform(translate=(0.0, 0.0, 0.0), scale=(1.0, 1.0, 1.0), rotate_x_deg=0.0) -> np.ndarray:
    """(4, 4) world_from_light = T R_x S (column vectors)."""
    angle = math.radians(rotate_x_deg)
    rotation = np.array([[1, 0, 0], [0, math.cos(angle), -math.sin(angle)], [0, math.sin(angle), math.cos(angle)]])
    matrix = np.eye(4)
    matrix[:3, :3] = rotation @ np.diag(scale)
    matrix[:3, 3] = translate
    return matrix


def uniform(num_points: int, num_samples: int, seed: int, dtype=torch.float64, device="cpu") -> torch.Tensor:
    """(num_points, num_samples, 2) seeded uniform numbers, drawn on the CPU (same on every device)."""
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(num_points, num_samples, 2, generator=generator, dtype=dtype).to(device)


def assert_estimate(samples: torch.Tensor, expected: float) -> None:
    """Mean of i.i.d. samples (S,) equals `expected` within NUM_SIGMA standard errors."""
    mean = samples.mean().item()
    standard_error = samples.std().item() / math.sqrt(samples.numel())
    assert abs(mean - expected) <= NUM_SIGMA * standard_error + 1e-12 * abs(expected), (
        f"estimate {mean} +- {standard_error} vs expected {expected}"
    )


def irradiance_by_light_sampling(
    light: Light, point, normal, num_samples: int, seed: int = 0, device="cpu"
) -> torch.Tensor:
    """(S,) per-sample estimates of the irradiance (first channel) at a point with a normal."""
    point = torch.tensor([point], dtype=torch.float64, device=device)
    sample = sample_light(light, point, uniform(1, num_samples, seed, device=device))
    cosine = (sample.direction[0] * torch.tensor(normal, dtype=torch.float64, device=device)).sum(-1).clamp_min(0.0)
    return sample.weight()[0, :, 0] * cosine


def irradiance_by_cosine_sampling(
    light: Light, point, normal, num_samples: int, seed: int = 1, device="cpu"
) -> torch.Tensor:
    """(S,) per-sample irradiance estimates from cosine-weighted directions (as BSDF rays would go)."""
    normal = torch.tensor(normal, dtype=torch.float64, device=device)
    local, pdf = cosine_hemisphere(uniform(1, num_samples, seed, device=device)[0])
    tangent, bitangent = orthonormal_basis(normal)
    directions = to_world(local, tangent, bitangent, normal)
    radiance = emitted_radiance(light, torch.tensor([point], dtype=torch.float64, device=device), directions)
    return radiance[:, 0] * local[:, 2] / pdf


# ---------------------------------------------------------------------------------------------
# Units: intensity, exposure, colour temperature, normalize.


def test_intensity_exposure_color():
    light = Light("/L", LightKind.RECT, intensity=3.0, exposure=2.0, color=(0.5, 1.0, 2.0))
    np.testing.assert_allclose(light_radiance_scale(light), [6.0, 12.0, 24.0])


@pytest.mark.parametrize("temperature, rgb", [(6500.0, (1.0433, 0.9836, 1.0346)), (3000.0, (1.771, 0.844, 0.272))])
def test_color_temperature_is_the_usdlux_blackbody_not_renormalised(temperature, rgb):
    light = Light("/L", LightKind.SPHERE, intensity=2.0, enable_color_temperature=True, color_temperature=temperature)
    np.testing.assert_allclose(light_radiance_scale(light), 2.0 * np.array(rgb), atol=2e-3)
    disabled = dataclasses.replace(light, enable_color_temperature=False)
    np.testing.assert_allclose(light_radiance_scale(disabled), [2.0, 2.0, 2.0])


@pytest.mark.parametrize(
    "light, area",
    [
        (Light("/R", LightKind.RECT, width=2.0, height=3.0, world_from_light=transform(scale=(2, 1, 5))), 12.0),
        (
            Light("/D", LightKind.DISK, radius=0.5, world_from_light=transform(scale=(3, 3, 1), rotate_x_deg=40)),
            math.pi * 0.25 * 9.0,
        ),
        (Light("/S", LightKind.SPHERE, radius=0.5, world_from_light=transform(scale=(2, 2, 2))), 4.0 * math.pi),
        (
            Light("/C", LightKind.CYLINDER, radius=0.5, length=2.0, world_from_light=transform(scale=(3, 2, 2))),
            12.0 * math.pi,
        ),
    ],
)
def test_normalize_divides_by_world_area(light, area):
    light = dataclasses.replace(light, intensity=10.0)
    assert size_factor(light) == pytest.approx(area)
    np.testing.assert_allclose(light_radiance_scale(dataclasses.replace(light, normalize=True)), 10.0 / area)
    np.testing.assert_allclose(light_radiance_scale(light), 10.0)


@pytest.mark.parametrize(
    "angle, expected",
    [
        (0.0, 1.0),
        (60.0, math.pi * 0.25),  # thetaMax 30 deg: pi sin^2
        (300.0, math.pi * (2.0 - 0.25)),  # thetaMax 150 deg: pi (2 - sin^2)
    ],
)
def test_distant_size_factor(angle, expected):
    assert size_factor(Light("/Sun", LightKind.DISTANT, angle=angle)) == pytest.approx(expected)


def test_default_distant_light_gives_3_36_lux_and_normalize_gives_its_intensity():
    sun = Light("/Sun", LightKind.DISTANT, intensity=50000.0, angle=0.53)
    estimate = irradiance_by_light_sampling(sun, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 4096)
    expected = 50000.0 * math.pi * math.sin(math.radians(0.265)) ** 2
    assert expected == pytest.approx(3.36, abs=5e-3)
    assert_estimate(estimate, expected)
    normalized = irradiance_by_light_sampling(dataclasses.replace(sun, normalize=True), (0, 0, 0), (0, 0, 1), 4096)
    assert_estimate(normalized, 50000.0)


def test_delta_distant_light_irradiance_is_its_radiance():
    # Local -Z (the light's travel) rotated by -90 deg about X is world -Y: the sun is overhead.
    sun = Light("/Sun", LightKind.DISTANT, intensity=5.0, angle=0.0, world_from_light=transform(rotate_x_deg=-90))
    sample = sample_light(sun, torch.zeros(2, 3), uniform(2, 3, 0, torch.float32))
    assert sample.is_delta
    np.testing.assert_allclose(sample.direction.numpy(), np.broadcast_to([0.0, 1.0, 0.0], (2, 3, 3)), atol=1e-6)
    np.testing.assert_allclose(sample.radiance.numpy(), 5.0)
    assert torch.isinf(sample.distance).all() and (sample.pdf == 1).all()
    assert (emitted_radiance(sun, torch.zeros(3), torch.tensor([0.0, 1.0, 0.0])) == 0).all()


def test_zero_radius_sphere_emits_intensity_over_four_only_when_normalized():
    point = Light("/P", LightKind.SPHERE, radius=0.0, intensity=8.0, world_from_light=transform((0, 0, 2)))
    receivers = torch.zeros(1, 3, dtype=torch.float64)
    dark = sample_light(point, receivers, uniform(1, 2, 0))
    assert dark.is_delta and (dark.radiance == 0).all()
    lit = sample_light(dataclasses.replace(point, normalize=True), receivers, uniform(1, 2, 0))
    np.testing.assert_allclose(lit.radiance.numpy(), 2.0 / 2.0**2)
    np.testing.assert_allclose(lit.distance.numpy(), 2.0)
    # The r -> 0 limit of a normalized sphere light: E = pi L (r/d)^2 = intensity / (4 d^2).
    small = dataclasses.replace(point, radius=1e-3, normalize=True)
    assert_estimate(irradiance_by_light_sampling(small, (0, 0, 0), (0, 0, 1), 2048), 2.0 / 4.0)


# ---------------------------------------------------------------------------------------------
# Irradiance from closed forms.


@pytest.mark.parametrize("radius, distance", [(0.5, 2.0), (1.0, 1.2), (0.01, 3.0)])
def test_sphere_irradiance_matches_pi_l_r2_over_d2(radius, distance):
    light = Light("/S", LightKind.SPHERE, radius=radius, intensity=3.0, world_from_light=transform((0, 0, distance)))
    estimate = irradiance_by_light_sampling(light, (0, 0, 0), (0, 0, 1), 20000)
    assert_estimate(estimate, math.pi * 3.0 * (radius / distance) ** 2)


def test_rect_irradiance_on_axis_matches_closed_form():
    width, height, distance = 2.0, 1.0, 1.5
    light = Light(
        "/R", LightKind.RECT, width=width, height=height, intensity=2.0, world_from_light=transform((0, 0, distance))
    )
    x, y = width / 2 / distance, height / 2 / distance
    closed_form = (
        2.0
        * 2.0
        * (
            x / math.hypot(1, x) * math.atan(y / math.hypot(1, x))
            + y / math.hypot(1, y) * math.atan(x / math.hypot(1, y))
        )
    )
    assert_estimate(irradiance_by_light_sampling(light, (0, 0, 0), (0, 0, 1), 20000), closed_form)


def test_one_sided_lights_emit_only_to_their_front():
    rect = Light("/R", LightKind.RECT, world_from_light=transform((0, 0, 1)))
    disk = Light("/D", LightKind.DISK, world_from_light=transform((0, 0, 1)))
    for light in (rect, disk):
        front = sample_light(light, torch.zeros(1, 3), uniform(1, 64, 0, torch.float32))
        back = sample_light(light, torch.tensor([[0.0, 0.0, 2.0]]), uniform(1, 64, 0, torch.float32))
        assert (front.radiance > 0).all() and (back.radiance == 0).all()
        assert torch.isinf(intersect_light(light, torch.tensor([0.0, 0.0, 2.0]), torch.tensor([0.0, 0.0, -1.0])))
        assert intersect_light(light, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0])) == pytest.approx(1.0)
    sphere = Light("/S", LightKind.SPHERE, radius=1.0)
    inside = sample_light(sphere, torch.tensor([[0.2, 0.0, 0.0]]), uniform(1, 16, 0, torch.float32))
    assert (inside.radiance == 0).all() and (inside.pdf == 0).all()


def test_rect_texture_faces_the_receiver_unmirrored():
    texture = np.array([[[1, 0, 0], [0, 1, 0]], [[0, 0, 1], [1, 1, 1]]], np.float32)  # row 0 = top
    rect = Light("/R", LightKind.RECT, texture=texture, world_from_light=transform((0, 0, 1)))
    # Seen from below (-Z, looking up +Z), local +X is on the viewer's left: pixel (0, 0) at (+X, +Y).
    receivers = torch.tensor([[0.25, 0.25, 0.0], [-0.25, 0.25, 0.0], [0.25, -0.25, 0.0], [-0.25, -0.25, 0.0]])
    radiance = emitted_radiance(rect, receivers, torch.tensor([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(radiance.numpy(), texture.reshape(4, 3), atol=1e-6)


def test_cylinder_emits_from_its_side_only():
    cylinder = Light("/C", LightKind.CYLINDER, radius=0.5, length=2.0)
    along_axis = torch.tensor([5.0, 0.0, 0.0])
    towards_cap = torch.tensor([-1.0, 0.0, 0.0])
    assert torch.isinf(intersect_light(cylinder, along_axis, towards_cap))
    side = torch.tensor([0.0, 3.0, 0.0])
    assert intersect_light(cylinder, side, torch.tensor([0.0, -1.0, 0.0])) == pytest.approx(2.5)
    np.testing.assert_allclose(emitted_radiance(cylinder, side, torch.tensor([0.0, -1.0, 0.0])).numpy(), 1.0)


# ---------------------------------------------------------------------------------------------
# Sampling densities: consistent with light_pdf, normalised, and MIS-compatible.

AREA_LIGHTS = [
    Light("/S", LightKind.SPHERE, radius=0.6, intensity=2.0, world_from_light=transform((0.3, 0.2, 1.5))),
    Light("/R", LightKind.RECT, width=1.5, height=1.0, world_from_light=transform((0, 0.3, 1.2), (1, 2, 1), 20)),
    Light("/D", LightKind.DISK, radius=0.8, world_from_light=transform((0.2, 0, 1.0), rotate_x_deg=-30)),
    Light("/C", LightKind.CYLINDER, radius=0.4, length=3.0, world_from_light=transform((0, 0, 1.0), (1, 1.5, 1.5))),
    Light("/Sun", LightKind.DISTANT, angle=50.0, world_from_light=transform(rotate_x_deg=-20)),
]


@pytest.mark.parametrize("light", AREA_LIGHTS, ids=lambda light: light.path)
def test_sample_pdf_equals_light_pdf_of_the_direction(light, device):
    points = torch.tensor([[0.0, 0.0, 0.0], [0.5, -0.3, 0.1]], dtype=torch.float64, device=device)
    sample = sample_light(light, points, uniform(2, 256, 3, device=device))
    torch.testing.assert_close(light_pdf(light, points.unsqueeze(1), sample.direction), sample.pdf)
    torch.testing.assert_close(emitted_radiance(light, points.unsqueeze(1), sample.direction), sample.radiance)
    hit = torch.isfinite(sample.distance)
    torch.testing.assert_close(intersect_light(light, points.unsqueeze(1), sample.direction)[hit], sample.distance[hit])


@pytest.mark.parametrize("light", AREA_LIGHTS, ids=lambda light: light.path)
def test_light_pdf_integrates_to_one_over_the_sphere(light, device):
    directions, density = uniform_sphere(uniform(1, 200000, 5, device=device)[0])
    ratio = light_pdf(light, torch.zeros(1, 3, dtype=torch.float64, device=device), directions) / density
    assert_estimate(ratio, 1.0)


@pytest.mark.parametrize("light", AREA_LIGHTS, ids=lambda light: light.path)
def test_light_and_bsdf_sampling_estimate_the_same_irradiance(light, device):
    normal = (0.0, 0.0, 1.0)
    by_light = irradiance_by_light_sampling(light, (0, 0, 0), normal, 20000, device=device)
    by_bsdf = irradiance_by_cosine_sampling(light, (0, 0, 0), normal, 200000, device=device)
    difference = by_light.mean() - by_bsdf.mean()
    standard_error = math.sqrt(by_light.var().item() / by_light.numel() + by_bsdf.var().item() / by_bsdf.numel())
    assert by_light.mean() > 0
    assert abs(difference.item()) <= NUM_SIGMA * standard_error


TEXTURED_DOME = Light("/Dome", LightKind.DOME, texture=np.ones((4, 8, 3), np.float32))


@pytest.mark.parametrize("light", AREA_LIGHTS + [TEXTURED_DOME], ids=lambda light: light.path)
def test_sampling_follows_the_input_device_and_dtype(light, device):
    points = torch.zeros(3, 3, dtype=torch.float32, device=device)
    sample = sample_light(light, points, uniform(3, 4, 0, torch.float32, device))
    for tensor in (sample.direction, sample.distance, sample.radiance, sample.pdf):
        assert tensor.dtype == torch.float32 and tensor.device == points.device
    assert sample.direction.shape == (3, 4, 3) and sample.pdf.shape == (3, 4)


def test_bad_shapes_raise():
    light = AREA_LIGHTS[1]
    with pytest.raises(ValueError, match=r"points must have shape \(\.\.\., 3\); got \(3, 2\)"):
        sample_light(light, torch.zeros(3, 2), uniform(3, 4, 0))
    with pytest.raises(ValueError, match=r"u must be \(N, S, 2\) of the points' dtype"):
        sample_light(light, torch.zeros(3, 3, dtype=torch.float64), uniform(2, 4, 0))
    with pytest.raises(ValueError, match="directions must have shape"):
        light_pdf(light, torch.zeros(3), torch.zeros(4))


def test_transforms_the_samplers_cannot_honour_are_rejected():
    with pytest.raises(ValueError, match="/S: SphereLight needs a rotation and one uniform scale"):
        validate_light(Light("/S", LightKind.SPHERE, world_from_light=transform(scale=(1, 2, 1))))
    with pytest.raises(ValueError, match="/C: CylinderLight needs"):
        validate_light(Light("/C", LightKind.CYLINDER, world_from_light=transform(scale=(1, 2, 1))))
    validate_light(Light("/C", LightKind.CYLINDER, world_from_light=transform(scale=(4, 2, 2), rotate_x_deg=30)))


@pytest.mark.parametrize(
    "light, message",
    [
        # 1e300 passed the 'finite' checks, then overflowed once squared (OverflowError in surface_area).
        (Light("/S", LightKind.SPHERE, radius=1e300), r"/S: inputs:radius gives a world-space size of 1e\+300"),
        (Light("/D", LightKind.DISK, radius=1e300), r"/D: inputs:radius gives a world-space size"),
        (Light("/C", LightKind.CYLINDER, radius=1e300, length=1e300), r"/C: inputs:length gives a world-space size"),
        (Light("/R", LightKind.RECT, width=1e30), r"/R: inputs:width gives a world-space size of 1e\+30"),
        # A light moved to 1e30 rendered non-finite pixels (squared distances overflow float32).
        (
            Light("/T", LightKind.RECT, world_from_light=transform(translate=(1e30, 0, 0))),
            r"/T: xformOp \(world transform\) puts the light at \(1e\+30, 0, 0\)",
        ),
        (Light("/X", LightKind.SPHERE, world_from_light=transform(scale=(1e20,) * 3)), r"/X: xformOp .* scales"),
        # exposure 1e30 raised OverflowError in 2.0**exposure; a diffuse of 1e300 rendered inf pixels.
        (Light("/E", LightKind.SPHERE, exposure=1e30), r"/E: inputs:intensity \* 2\^inputs:exposure .* emits inf nits"),
        (Light("/F", LightKind.SPHERE, diffuse=1e300), r"/F: inputs:intensity .* emits 1e\+300 nits, beyond 1e\+20"),
        (
            Light("/N", LightKind.RECT, normalize=True, width=1e-30, height=1e-30),
            r"/N: inputs:intensity .* emits 1e\+60 nits",
        ),
    ],
)
def test_lights_beyond_float32_arithmetic_are_refused_naming_the_input(light, message):
    with pytest.raises(ValueError, match=message):
        validate_light(light)


def test_largest_accepted_lights_render_finite_radiance():
    # At the bounds (MAX_EXTENT, MAX_RADIANCE) the float32 sampler still gives finite weights.
    big = Light("/B", LightKind.SPHERE, radius=1e15, intensity=1e20, world_from_light=transform(translate=(1e15, 0, 0)))
    bright = Light("/L", LightKind.SPHERE, radius=1e-3, intensity=1e20)
    for light in (big, bright):
        validate_light(light)
        points = torch.tensor([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [5e14, 3.0, 0.0]], dtype=torch.float32)
        sample = sample_light(light, points, uniform(3, 8, 0, dtype=torch.float32))
        assert torch.isfinite(sample.weight()).all() and torch.isfinite(sample.pdf).all()


# ---------------------------------------------------------------------------------------------
# Dome light.


def dome_texture(height: int = 16, width: int = 32, seed: int = 0) -> np.ndarray:
    """A lat-long image with a bright 'sun' patch over a dim sky."""
    rng = np.random.default_rng(seed)
    texture = rng.uniform(0.05, 0.2, (height, width, 3)).astype(np.float32)
    texture[3:5, 20:22] = (40.0, 30.0, 20.0)
    return texture


def test_dome_pdf_integrates_to_one(device):
    dome = Light("/Dome", LightKind.DOME, texture=dome_texture(), world_from_light=transform(rotate_x_deg=25))
    # Midpoint rule on a grid four times finer than the pixels: pdf_uv is constant on each cell.
    num_theta, num_phi = 64, 128
    theta = (torch.arange(num_theta, dtype=torch.float64, device=device) + 0.5) / num_theta * math.pi
    phi = (torch.arange(num_phi, dtype=torch.float64, device=device) + 0.5) / num_phi * 2 * math.pi
    theta, phi = torch.meshgrid(theta, phi, indexing="ij")
    local = torch.stack((torch.sin(theta) * torch.sin(phi), torch.cos(theta), torch.sin(theta) * torch.cos(phi)), -1)
    world = local @ torch.as_tensor(dome.world_from_light[:3, :3], device=device).T
    solid_angle = torch.sin(theta) * (math.pi / num_theta) * (2 * math.pi / num_phi)
    total = (light_pdf(dome, torch.zeros(3, dtype=torch.float64, device=device), world) * solid_angle).sum()
    # Exact up to the sin(theta) of the cell centre versus the pixel centre: O(1/num_theta^2).
    assert total.item() == pytest.approx(1.0, abs=2e-3)


def test_dome_importance_and_uniform_sampling_agree(device):
    dome = Light(
        "/Dome", LightKind.DOME, intensity=1.5, texture=dome_texture(), world_from_light=transform(rotate_x_deg=25)
    )
    normal = (0.0, 0.6, 0.8)
    importance = irradiance_by_light_sampling(dome, (0, 0, 0), normal, 20000, device=device)
    directions, density = uniform_sphere(uniform(1, 400000, 7, device=device)[0])
    cosine = (directions * torch.tensor(normal, dtype=torch.float64, device=device)).sum(-1).clamp_min(0.0)
    origin = torch.zeros(3, dtype=torch.float64, device=device)
    uniform_estimate = emitted_radiance(dome, origin, directions)[:, 0] * cosine / density
    standard_error = math.sqrt(
        importance.var().item() / importance.numel() + uniform_estimate.var().item() / uniform_estimate.numel()
    )
    assert abs(importance.mean().item() - uniform_estimate.mean().item()) <= NUM_SIGMA * standard_error
    # Importance sampling is the point: far lower variance than uniform for a dome with a sun.
    assert importance.var() < 0.1 * uniform_estimate.var()


def test_untextured_dome_gives_pi_l():
    dome = Light("/Dome", LightKind.DOME, intensity=2.0, color=(1.0, 0.5, 0.25))
    estimate = irradiance_by_light_sampling(dome, (0, 0, 0), (0.0, 0.0, 1.0), 8000)
    assert_estimate(estimate, 2.0 * math.pi)


@pytest.mark.parametrize(
    "pole_axis, direction, row, col",
    [
        ("Y", (1.0, -0.02, 0.05), 4, 4),  # longitude ~+pi/2 -> u ~ 0.258; just below the equator -> v ~ 0.506
        ("Y", (-0.05, -0.02, 1.0), 4, 8),  # longitude ~0 -> u ~ 0.508
        ("Y", (0.0, 1.0, 0.0), 0, None),  # top pole -> row 0
        ("Z", (-0.05, -1.0, -0.02), 4, 8),  # DomeLight_1 poleAxis Z: longitude 0 points to -Y
        ("Z", (0.0, 0.0, 1.0), 0, None),  # and the top pole is +Z
    ],
)
def test_dome_latlong_orientation(pole_axis, direction, row, col):
    texture = np.zeros((8, 16, 3), np.float32)
    texture[row, slice(None) if col is None else col] = 10.0
    dome = Light("/Dome", LightKind.DOME, texture=texture, pole_axis=pole_axis)
    along = torch.nn.functional.normalize(torch.tensor(direction), dim=-1)
    np.testing.assert_allclose(emitted_radiance(dome, torch.zeros(3), along).numpy(), 10.0)
    assert emitted_radiance(dome, torch.zeros(3), -along).sum() == 0
