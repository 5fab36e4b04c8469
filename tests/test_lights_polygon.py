"""The closed-form irradiance of a RectLight (lights/polygon.py) against its closed form on the
axis and against Monte Carlo light sampling through `sample_light` (the same integral)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from relight_torch.lights import polygon
from relight_torch.lights.emission import sample_light
from relight_torch.lights.light import Light, LightKind
from relight_torch.lights.polygon import rect_cosine_integral
from relight_torch.lights.ratio import analytic_ratio, has_closed_form
from relight_torch.math.frame import dot


def world_from_light(translate, rotation_deg=(0.0, 0.0), scale=(1.0, 1.0, 1.0)) -> np.ndarray:
    """(4, 4) T R_y R_x S."""
    ax, ay = (math.radians(a) for a in rotation_deg)
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    matrix = np.eye(4)
    matrix[:3, :3] = ry @ rx @ np.diag(scale)
    matrix[:3, 3] = translate
    return matrix


def monte_carlo(light: Light, points: torch.Tensor, normals: torch.Tensor, num_samples: int):
    """(mean, standard error) (N,) of cos+ / pdf over the light's own samples (`sample_light`, the
    reference's sampler): its unshadowed irradiance at unit radiance."""
    u = torch.rand(points.shape[0], num_samples, 2, generator=torch.Generator().manual_seed(3), dtype=points.dtype)
    sample = sample_light(light, points, u)
    estimate = (
        torch.isfinite(sample.distance)
        * dot(sample.direction, normals.unsqueeze(1)).clamp_min(0.0)
        * sample.inverse_pdf()
    )
    return estimate.mean(1), estimate.std(1) / math.sqrt(num_samples)


def test_square_on_axis_matches_the_closed_form():
    side, distance = 2.0, 1.5
    light = Light("/R", LightKind.RECT, width=side, height=side, world_from_light=world_from_light((0, 0, distance)))
    x = side / 2 / distance
    closed_form = 4.0 * x / math.hypot(1, x) * math.atan(x / math.hypot(1, x))
    points = torch.zeros(1, 3, dtype=torch.float64)
    value = rect_cosine_integral(light, points, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
    assert float(value) == pytest.approx(closed_form, rel=1e-12)
    # A receiver facing away sees nothing; one facing sideways sees exactly half (clipped at the horizon).
    assert float(rect_cosine_integral(light, points, torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64))) == 0.0
    sideways = rect_cosine_integral(light, points, torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64))
    assert float(sideways) == pytest.approx(
        float(
            rect_cosine_integral(
                light,
                torch.tensor([[-1e-9, 0.0, 0.0]], dtype=torch.float64),
                torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64),
            )
        ),
        rel=1e-6,
    )


@pytest.mark.parametrize(
    "light",
    [
        Light("/R", LightKind.RECT, width=1.3, height=0.7, world_from_light=world_from_light((0.2, 0.1, 1.0))),
        Light(
            "/T",
            LightKind.RECT,
            width=0.8,
            height=1.1,
            normalize=True,
            world_from_light=world_from_light((0.0, 0.3, 0.6), (35.0, -20.0), (1.5, 0.6, 2.0)),
        ),
    ],
)
def test_random_receivers_match_monte_carlo_including_horizon_clipped_ones(light):
    generator = torch.Generator().manual_seed(11)
    points = (torch.rand(48, 3, generator=generator, dtype=torch.float64) - 0.5) * 2.0 + torch.tensor([0.0, 0.0, 0.4])
    normals = torch.nn.functional.normalize(torch.randn(48, 3, generator=generator, dtype=torch.float64), dim=-1)
    exact = rect_cosine_integral(light, points, normals)
    mean, error = monte_carlo(light, points, normals, 40000)
    assert (exact - mean).abs().max() <= (4.5 * error).max() + 1e-9
    # The draw holds every case: lit whole, clipped by the horizon, facing away, behind the light.
    local = (points - torch.as_tensor(light.world_from_light[:3, 3])) @ torch.as_tensor(
        np.linalg.inv(light.world_from_light[:3, :3])
    ).T
    assert int((local[:, 2] >= 0).sum()) >= 3 and int(((mean > 0) & (local[:, 2] < 0)).sum()) >= 20
    corners = torch.as_tensor(
        light.world_from_light[:3, :3]
        @ np.array([[s * light.width / 2, t * light.height / 2, 0.0] for s in (-1, 1) for t in (-1, 1)]).T
        + light.world_from_light[:3, 3:]
    ).T  # (4, 3)
    heights = ((corners.unsqueeze(1) - points) * normals).sum(-1)
    straddling = (heights.max(0).values > 0) & (heights.min(0).values < 0) & (local[:, 2] < 0)
    assert int(straddling.sum()) >= 5


def test_blocks_of_receivers_give_the_values_of_one_and_no_receivers_none(monkeypatch):
    light = Light("/R", LightKind.RECT, width=1.3, height=0.7, world_from_light=world_from_light((0.2, 0.1, 1.0)))
    generator = torch.Generator().manual_seed(5)
    points = (torch.rand(48, 3, generator=generator) - 0.5) * 2.0
    normals = torch.nn.functional.normalize(torch.randn(48, 3, generator=generator), dim=-1)
    whole = rect_cosine_integral(light, points, normals)
    monkeypatch.setattr(polygon, "CHUNK_POINTS", 7)  # to rounding: vector loops and their scalar tails
    torch.testing.assert_close(rect_cosine_integral(light, points, normals), whole, rtol=1e-6, atol=1e-7)
    assert rect_cosine_integral(light, points[:0], normals[:0]).shape == (0,)


def test_ratio_is_exact_for_any_unshadowed_samples_and_only_for_rect_lights_without_texture_among_planar_ones():
    light = Light("/R", LightKind.RECT, width=1.0, height=0.5, world_from_light=world_from_light((0, 0, 1.0)))
    points = torch.tensor([[0.1, 0.2, 0.0], [0.4, -0.3, 0.2]], dtype=torch.float64)
    normals = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]], dtype=torch.float64)
    few, _ = monte_carlo(light, points, normals, 2)
    ratio = analytic_ratio(light, points, normals, few)
    assert torch.allclose(ratio * few, rect_cosine_integral(light, points, normals), rtol=1e-12)
    assert torch.equal(
        analytic_ratio(light, points, normals, torch.zeros(2, dtype=torch.float64)), torch.ones(2, dtype=torch.float64)
    )
    textured = Light("/T", LightKind.RECT, texture=np.ones((2, 2, 3), np.float32))
    assert not has_closed_form(textured) and analytic_ratio(textured, points, normals, few) is None
    assert not has_closed_form(Light("/D", LightKind.DISK)) and not has_closed_form(
        Light("/Z", LightKind.RECT, width=0.0)
    )
