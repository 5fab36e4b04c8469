"""GGX distributions, Smith masking, Schlick Fresnel and visible-normal sampling."""

from __future__ import annotations

import math

import pytest
import torch

from relight_torch.math import microfacet
from relight_torch.math.sampling import hemisphere_quadrature

DTYPE = torch.float64


def _direction(theta: float, phi: float = 0.4, device=None) -> torch.Tensor:
    return torch.tensor(
        [math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)], dtype=DTYPE, device=device
    )


@pytest.mark.parametrize("alpha", [0.05, 0.3, 1.0])
def test_ggx_is_normalised_and_storm_variant_is_scaled(device, alpha):
    # Projected-area normalisation: the integral of D(h) cos(theta_h) over the hemisphere is 1.
    h, weights = hemisphere_quadrature(4096, 4, device=device, dtype=DTYPE)
    alpha_t = torch.tensor(alpha, dtype=DTYPE, device=device)
    exact = float((microfacet.ggx_d(h[:, 2], alpha_t) * h[:, 2] * weights).sum())
    storm = float((microfacet.storm_ggx_d(h[:, 2], alpha_t) * h[:, 2] * weights).sum())
    assert exact == pytest.approx(1.0, abs=2e-4)
    # Storm's EPSILON: the lobe integrates to (a^2 + 0.001)/a^2, not 1.
    assert storm == pytest.approx((alpha**2 + 0.001) / alpha**2, rel=2e-4)


def test_ggx_at_the_normal_by_hand():
    # D(cos_h = 1) = a^2 / (pi a^4) = 1/(pi a^2); Storm's = (a^2 + 0.001)/(pi a^4).
    alpha = torch.tensor(0.25, dtype=DTYPE)
    one = torch.tensor(1.0, dtype=DTYPE)
    assert float(microfacet.ggx_d(one, alpha)) == pytest.approx(1 / (math.pi * 0.0625))
    assert float(microfacet.storm_ggx_d(one, alpha)) == pytest.approx(0.0635 / (math.pi * 0.00390625))


def test_ggx_float32_at_tiny_roughness():
    # roughness 0.001 -> alpha 1e-6: the textbook denominator cancels to 0 in float32 near cos 1.
    alpha = torch.tensor(1e-6)
    cos_h = torch.tensor([1.0, 0.9999999, 0.99])
    value = microfacet.ggx_d(cos_h, alpha)
    assert torch.all(torch.isfinite(value))
    assert float(value[0]) == pytest.approx(1 / (math.pi * 1e-12), rel=1e-5)


@pytest.mark.parametrize("alpha", [0.1, 0.5, 1.0])
@pytest.mark.parametrize("theta_o", [0.0, 0.7, 1.4])
def test_visible_normal_pdf_integrates_to_one(device, alpha, theta_o):
    # int G1(wo) max(0, wo.h) D(h) / wo.z dh = 1 holds only if G1 is the exact Smith masking of D.
    h, weights = hemisphere_quadrature(1024, 256, device=device, dtype=DTYPE)
    wo = _direction(theta_o, device=device).expand_as(h)
    alpha_t = torch.tensor(alpha, dtype=DTYPE, device=device)
    integral = float((microfacet.ggx_visible_normal_pdf(wo, h, alpha_t) * weights).sum())
    assert integral == pytest.approx(1.0, abs=2e-3)


def test_smith_and_schlick_masking_limits():
    alpha = torch.tensor(0.4, dtype=DTYPE)
    cosines = torch.tensor([0.0, 0.3, 1.0], dtype=DTYPE)
    g1 = microfacet.smith_g1_ggx(cosines, alpha)
    assert g1.tolist()[0] == 0.0 and g1.tolist()[2] == pytest.approx(1.0)
    # G1 = 2/(1 + sqrt(1 + a^2 tan^2)) at cos 0.3 by hand.
    tan2 = (1 - 0.09) / 0.09
    assert float(g1[1]) == pytest.approx(2 / (1 + math.sqrt(1 + 0.16 * tan2)))
    # Storm's k = a/2: G(1, 0.3) = 1 * 0.3/(0.3 (1 - 0.2) + 0.2).
    g = microfacet.storm_schlick_ggx_g(torch.tensor(1.0, dtype=DTYPE), torch.tensor(0.3, dtype=DTYPE), alpha)
    assert float(g) == pytest.approx(0.3 / (0.3 * 0.8 + 0.2))


def test_schlick_fresnel_endpoints_and_midpoint():
    f0 = torch.tensor([0.04, 0.5, 0.9], dtype=DTYPE)
    f90 = torch.tensor(1.0, dtype=DTYPE)
    assert torch.allclose(microfacet.schlick_fresnel(f0, f90, torch.tensor(1.0, dtype=DTYPE)), f0)
    grazing = microfacet.schlick_fresnel(f0, f90, torch.tensor(0.0, dtype=DTYPE))
    assert torch.allclose(grazing, torch.ones(3, dtype=DTYPE))
    half = microfacet.schlick_fresnel(f0, f90, torch.tensor(0.5, dtype=DTYPE))
    assert torch.allclose(half, f0 + (1 - f0) / 32)


def test_visible_normal_samples_are_visible_and_reflections_match_pdf(device, tolerances):
    generator = torch.Generator().manual_seed(5)
    u = torch.rand(4096, 2, generator=generator, dtype=DTYPE).to(device)
    wo = _direction(1.1, device=device).expand(4096, 3)
    alpha = torch.tensor(0.3, dtype=DTYPE, device=device)
    h = microfacet.sample_ggx_visible_normal(wo, alpha, u)
    torch.testing.assert_close(h.norm(dim=-1), torch.ones(4096, dtype=DTYPE, device=device), **tolerances[DTYPE])
    assert torch.all(h[:, 2] >= 0) and torch.all((wo * h).sum(-1) >= -1e-12)
    wi, pdf = microfacet.sample_ggx_reflection(wo, alpha, u)
    torch.testing.assert_close(pdf, microfacet.ggx_reflection_pdf(wo, wi, alpha), **tolerances[DTYPE])
    assert torch.all(pdf[wi[:, 2] <= 0] == 0)
