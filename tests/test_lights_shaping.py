"""ShapingAPI, RelightBarzelLightAPI and ShadowAPI factors against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from relight_torch.lights.emission import emitted_radiance
from relight_torch.lights.light import BarzelShaping, Light, LightKind, Shadow, Shaping
from relight_torch.lights.shadow import shadow_factor
from relight_torch.lights.shaping import barzel_factor, shaping_factor


def emission(theta_deg: float, azimuth_deg: float = 0.0) -> torch.Tensor:
    """Light-local unit emission direction at angle theta from the -Z axis, azimuth from +X."""
    theta, azimuth = math.radians(theta_deg), math.radians(azimuth_deg)
    return torch.tensor(
        [math.sin(theta) * math.cos(azimuth), math.sin(theta) * math.sin(azimuth), -math.cos(theta)],
        dtype=torch.float64,
    )


def projected(x: float, y: float) -> torch.Tensor:
    """The unit emission direction through (x, y) on the plane one unit in front of the light."""
    return torch.nn.functional.normalize(torch.tensor([x, y, -1.0], dtype=torch.float64), dim=-1)


@pytest.mark.parametrize(
    "theta, expected",
    [
        (10.0, 1.0),  # inside theta_start = 30 (1 - 0.5) = 15 deg
        (20.0, 20.0 / 27.0),  # t = 1/3: 1 - t^2 (3 - 2t) = 1 - 7/27
        (22.5, 0.5),  # halfway
        (31.0, 0.0),  # beyond the half-angle
    ],
)
def test_cone_with_softness(theta, expected):
    factor = shaping_factor(Shaping(cone_angle=30.0, cone_softness=0.5), emission(theta))
    np.testing.assert_allclose(factor.numpy(), expected, atol=1e-12)


def test_hard_cone_and_softness_clamped_to_one():
    hard = Shaping(cone_angle=30.0)
    assert shaping_factor(hard, emission(29.9)).min() == 1.0 and shaping_factor(hard, emission(30.1)).max() == 0.0
    soft = shaping_factor(Shaping(cone_angle=30.0, cone_softness=3.0), emission(15.0))
    np.testing.assert_allclose(soft.numpy(), 0.5, atol=1e-12)  # softness 1: ramp over [0, 30] deg


def test_focus_and_focus_tint():
    focused = Shaping(focus=2.0, focus_tint=(1.0, 0.0, 0.5), cone_angle=180.0)
    # |cos 60|^2 = 1/4, tinted: tint + 1/4 (1 - tint).
    np.testing.assert_allclose(shaping_factor(focused, emission(60.0)).numpy(), [1.0, 0.25, 0.625])
    np.testing.assert_allclose(shaping_factor(focused, emission(0.0)).numpy(), [1.0, 1.0, 1.0])
    ignored = Shaping(focus=-1.0, cone_angle=180.0)
    np.testing.assert_allclose(shaping_factor(ignored, emission(60.0)).numpy(), 1.0)


def test_shaping_reaches_emitted_radiance_of_an_area_light():
    # A small disk at the origin facing -Z; receivers 10 units away at theta off its axis look at its centre.
    disk = Light("/D", LightKind.DISK, radius=0.01, shaping=Shaping(cone_angle=30.0, cone_softness=0.5))
    receivers = torch.stack([10.0 * emission(theta) for theta in (10.0, 22.5, 40.0)])
    radiance = emitted_radiance(disk, receivers, -torch.nn.functional.normalize(receivers, dim=-1))
    np.testing.assert_allclose(radiance[:, 0].numpy(), [1.0, 0.5, 0.0], atol=1e-9)


def test_sphere_light_without_shaping_emits_backwards_and_fallback_cone_cuts_it():
    receiver = torch.tensor([0.0, 0.0, 5.0], dtype=torch.float64)  # behind the light (+Z side)
    towards_light = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    sphere = Light("/S", LightKind.SPHERE)
    assert emitted_radiance(sphere, receiver, towards_light)[0] == 1.0
    focus_only = Light("/S", LightKind.SPHERE, shaping=Shaping(focus=0.0))  # fallback coneAngle 90
    assert emitted_radiance(focus_only, receiver, towards_light)[0] == 0.0


# ---------------------------------------------------------------------------------------------
# Barzel.


def barzel_at(barzel: BarzelShaping, direction: torch.Tensor, distance: float = 1.0) -> np.ndarray:
    return barzel_factor(barzel, direction, torch.tensor(distance, dtype=torch.float64)).numpy()


def test_barzel_fallbacks_change_nothing():
    for direction in (emission(0.0), emission(80.0, 30.0), emission(170.0, 200.0)):
        np.testing.assert_allclose(barzel_at(BarzelShaping(), direction, 7.0), 1.0)


def test_window_superellipse_roundness_and_edge():
    half = 0.5  # width = height = 1: half-size 0.5 at unit distance
    corner = projected(0.9 * half, 0.9 * half)  # inside the square, outside the circle (q = 0.9 sqrt 2)
    ellipse = BarzelShaping(window_enable=True)
    square = BarzelShaping(window_enable=True, window_roundness=0.0)
    assert barzel_at(ellipse, corner)[0] == 0.0 and barzel_at(square, corner)[0] == 1.0
    soft = BarzelShaping(window_enable=True, window_edge=0.5, window_height=2.0)
    np.testing.assert_allclose(barzel_at(soft, projected(0.75 * half, 0.0)), 0.5)  # smoothstep(0.5, 1, 0.75)
    np.testing.assert_allclose(barzel_at(soft, projected(0.0, 0.75 * 2 * half)), 0.5)
    assert barzel_at(ellipse, emission(100.0))[0] == 0.0  # behind the light


def test_window_roundness_two_is_a_diamond():
    diamond = BarzelShaping(window_enable=True, window_roundness=2.0)  # n = 1: |2x| + |2y| <= 1
    assert barzel_at(diamond, projected(0.24, 0.24))[0] == 1.0
    assert barzel_at(diamond, projected(0.26, 0.26))[0] == 0.0


def test_barn_doors():
    doors = BarzelShaping(barn_door_right=30.0, barn_door_top=10.0)
    assert barzel_at(doors, emission(40.0, 0.0))[0] == 0.0  # towards +X, past the right door
    assert barzel_at(doors, emission(40.0, 180.0))[0] == 1.0  # towards -X: left door open
    assert barzel_at(doors, emission(20.0, 0.0))[0] == 1.0
    assert barzel_at(doors, emission(15.0, 90.0))[0] == 0.0  # towards +Y, past the top door
    assert barzel_at(doors, emission(15.0, 270.0))[0] == 1.0


@pytest.mark.parametrize(
    "smooth, distance, expected",
    [
        (False, 0.5, 0.0),
        (False, 1.5, 0.25),
        (False, 2.0, 0.5),
        (False, 4.0, 1.0),
        (False, 6.5, 0.25),
        (False, 8.0, 0.0),
        (True, 1.5, 0.15625),
        (True, 6.5, 1.0 - 0.84375),
    ],
)
def test_near_and_far_falloff(smooth, distance, expected):
    falloff = BarzelShaping(near_start=1.0, near_end=3.0, far_start=5.0, far_end=7.0, falloff_smooth=smooth)
    np.testing.assert_allclose(barzel_at(falloff, emission(0.0), distance), expected)


def test_cookie_projection_and_orientation():
    cookie = np.zeros((2, 2, 3), np.float32)
    cookie[0, 1] = (1.0, 2.0, 3.0)  # top-right pixel: st (0.75, 0.75)
    barzel = BarzelShaping(cookie=cookie, cookie_scale=(2.0, 1.0), cookie_offset=(0.5, 0.0))
    # st = 0.5 + (p - offset) / (2 scale) = (0.75, 0.75) at p = (1.5, 0.5).
    np.testing.assert_allclose(barzel_at(barzel, projected(1.5, 0.5)), [1.0, 2.0, 3.0], rtol=1e-6)
    assert barzel_at(barzel, projected(-0.5, 0.5)).sum() == 0.0  # st (0.25, 0.75): top-left, black
    assert barzel_at(barzel, projected(3.0, 0.0)).sum() == 0.0  # outside the cookie's rectangle
    assert barzel_at(barzel, emission(120.0)).sum() == 0.0  # behind the light


def test_barzel_reaches_emitted_radiance_with_world_distance():
    barzel = BarzelShaping(far_start=2.0, far_end=4.0, falloff_smooth=False)
    world_from_light = np.eye(4)
    world_from_light[:3, 3] = (0.0, 0.0, 10.0)
    sphere = Light("/S", LightKind.SPHERE, radius=0.1, barzel=barzel, world_from_light=world_from_light)
    receivers = torch.tensor([[0.0, 0.0, 7.0], [0.0, 0.0, 3.0]], dtype=torch.float64)  # 3 and 7 from the origin
    radiance = emitted_radiance(sphere, receivers, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    np.testing.assert_allclose(radiance[:, 0].numpy(), [0.5, 0.0])


# ---------------------------------------------------------------------------------------------
# Shadows.


def test_shadow_colour_distance_and_falloff():
    shadow = Shadow(color=(0.2, 0.5, 1.0), distance=10.0, falloff=4.0, falloff_gamma=2.0)
    occluded = torch.tensor([True, True, True, False])
    distance = torch.tensor([8.0, 5.0, 11.0, 1.0], dtype=torch.float64)
    # At 8: fade ((10 - 8) / 4)^2 = 1/4 -> 1 - (1 - colour) / 4; at 5: full shadow = colour; at 11: none.
    expected = [[0.8, 0.875, 1.0], [0.2, 0.5, 1.0], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0]]
    np.testing.assert_allclose(shadow_factor(shadow, occluded, distance).numpy(), expected)


def test_shadow_defaults_and_disabled():
    occluded = torch.tensor([True, False])
    distance = torch.tensor([1e6, 0.0])
    np.testing.assert_allclose(shadow_factor(Shadow(), occluded, distance).numpy(), [[0, 0, 0], [1, 1, 1]])
    hard_limit = Shadow(distance=2.0)
    np.testing.assert_allclose(
        shadow_factor(hard_limit, torch.tensor([True, True]), torch.tensor([1.0, 3.0])).numpy(), [[0, 0, 0], [1, 1, 1]]
    )
    np.testing.assert_allclose(shadow_factor(Shadow(enable=False), occluded, distance).numpy(), 1.0)
