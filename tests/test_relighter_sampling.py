"""How many samples a light gets: its angular radius and the adaptive count (hand-computed values);
the supersampling box filter against the plain block mean."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from relight_torch.direct.images import box_filter
from relight_torch.light_samples import adaptive_sample_count, angular_radius
from relight_torch.lights.light import Light, LightKind


def placed(kind: LightKind, scale: float = 1.0, **fields) -> Light:
    world_from_light = np.diag([scale, scale, scale, 1.0])
    world_from_light[:3, 3] = (0.0, 10.0, 0.0)
    return Light("/L", kind, world_from_light, **fields)


POINTS = torch.tensor([[0.0, 0.0, 0.0], [0.0, 6.0, 0.0], [30.0, 10.0, 0.0]])  # nearest: 4 from the light


@pytest.mark.parametrize(
    ("light", "expected"),
    [
        (placed(LightKind.SPHERE, radius=2.0), math.asin(2.0 / 4.0)),  # 30 degrees
        (placed(LightKind.SPHERE, scale=0.5, radius=2.0), math.asin(1.0 / 4.0)),  # world radius 1
        (placed(LightKind.RECT, width=6.0, height=8.0), math.pi / 2),  # half-diagonal 5 > 4
        (placed(LightKind.RECT, width=3.0, height=4.0), math.asin(2.5 / 4.0)),
        (placed(LightKind.DISK, radius=1.0), math.asin(1.0 / 4.0)),
        (placed(LightKind.CYLINDER, radius=1.5, length=4.0), math.asin(2.5 / 4.0)),  # hypot(2, 1.5)
        (placed(LightKind.DISTANT, angle=0.53), math.radians(0.265)),
        (placed(LightKind.SPHERE, radius=0.0), 0.0),
        (placed(LightKind.DOME), math.pi),
    ],
)
def test_angular_radius(light, expected):
    assert angular_radius(light, POINTS) == pytest.approx(expected, rel=1e-6)


def test_adaptive_sample_count():
    full = math.radians(10.0)
    assert adaptive_sample_count(16, 1, full, full) == 16
    assert adaptive_sample_count(16, 1, math.radians(30.0), full) == 16
    # sin^2(5 deg) / sin^2(10 deg) = 0.2519: 16 x 0.2519 = 4.03, rounded up.
    assert adaptive_sample_count(16, 1, math.radians(5.0), full) == 5
    assert adaptive_sample_count(16, 1, math.radians(0.5), full) == 1
    assert adaptive_sample_count(16, 4, math.radians(0.5), full) == 4
    assert adaptive_sample_count(16, 1, math.radians(0.5), 0.0) == 16  # adaptivity off


@pytest.mark.parametrize("s", [1, 2, 3])
def test_box_filter_is_the_block_mean(s):
    image = torch.rand(4 * s, 6 * s, 3, generator=torch.Generator().manual_seed(s))
    expected = image.reshape(4, s, 6, s, 3).mean(dim=(1, 3))
    torch.testing.assert_close(box_filter(image, s), expected, rtol=1e-6, atol=1e-7)
