"""Hand-computed BRDF values, closed-form albedos, gradients and argument checks."""

from __future__ import annotations

import math

import pytest
import torch

from relight_torch import brdf
from relight_torch.brdf import blinn_phong
from relight_torch.math.sampling import hemisphere_quadrature

DTYPE = torch.float64


def _t(*values, device=None) -> torch.Tensor:
    return torch.tensor([values] if len(values) == 3 else values, dtype=DTYPE, device=device)


def _direction(theta_deg: float, phi: float = 0.0, device=None) -> torch.Tensor:
    theta = math.radians(theta_deg)
    components = [math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)]
    return torch.tensor([components], dtype=DTYPE, device=device)


NORMAL = _direction(0.0)


def _albedo(module, params, wo: torch.Tensor, num_theta: int = 1024, num_phi: int = 512) -> torch.Tensor:
    """Directional albedo (3,) of `module` at wo (1, 3) by midpoint quadrature."""
    wi, weights = hemisphere_quadrature(num_theta, num_phi, device=wo.device, dtype=DTYPE)
    value = module.eval(params, wo.expand_as(wi), wi)
    return (value * (wi[:, 2] * weights)[:, None]).sum(0)


def test_lambert_is_albedo_over_pi(device, tolerances):
    params = brdf.LambertParams(_t(0.8, 0.5, 0.2, device=device))
    value = brdf.lambert.eval(params, _direction(40, 0.3, device), _direction(70, 2.0, device))
    torch.testing.assert_close(value, _t(0.8, 0.5, 0.2, device=device) / math.pi, **tolerances[DTYPE])


def test_phong_peak_and_normal_incidence_albedo(device, tolerances):
    params = brdf.PhongParams(_t(0.5, 0.5, 0.5, device=device), _t(10.0, device=device))
    # Peak at wi = mirror(wo) = n: ks (n + 2)/(2 pi) = 0.5 * 12 / (2 pi).
    torch.testing.assert_close(
        brdf.phong.eval(params, NORMAL.to(device), NORMAL.to(device)),
        torch.full((1, 3), 0.954929658551372, dtype=DTYPE, device=device),
        **tolerances[DTYPE],
    )
    assert _albedo(brdf.phong, params, NORMAL.to(device)).tolist() == pytest.approx([0.5] * 3, abs=1e-5)


def test_blinn_phong_normalisation(device):
    # c(10) = 12 * 14 / (8 pi (2^-5 + 10)) by hand; albedo at normal incidence = ks.
    assert float(blinn_phong.normalization(torch.tensor(10.0))) == pytest.approx(0.6663683598613935)
    for exponent in (0.0, 3.0, 40.0):
        params = brdf.BlinnPhongParams(_t(1.0, 1.0, 1.0, device=device), _t(exponent, device=device))
        assert _albedo(brdf.blinn_phong, params, NORMAL.to(device)).tolist() == pytest.approx([1.0] * 3, abs=1e-4)


def test_cook_torrance_at_normal_incidence(device, tolerances):
    # wo = wi = n: D = 1/(pi a^2), G = 1, F = f0 -> f = f0 / (4 pi a^2); a = 0.3.
    params = brdf.CookTorranceParams(_t(0.04, 0.5, 1.0, device=device), _t(0.3, device=device))
    expected = _t(0.04, 0.5, 1.0, device=device) * 0.8841941282883075
    torch.testing.assert_close(brdf.cook_torrance.eval(params, NORMAL.to(device), NORMAL.to(device)), expected)


def test_oren_nayar_by_hand_and_lambert_limit(device, tolerances):
    albedo = _t(0.8, 0.5, 0.2, device=device)
    wo, wi = _direction(60.0, device=device), _direction(30.0, device=device)
    # sigma 0.5: A = 0.784483, B = 0.330882; same azimuth: sin(60) tan(30) = 0.5.
    params = brdf.OrenNayarParams(albedo, _t(0.5, device=device))
    torch.testing.assert_close(brdf.oren_nayar.eval(params, wo, wi), albedo * 0.3023701796621633, **tolerances[DTYPE])
    lambert = brdf.lambert.eval(brdf.LambertParams(albedo), wo, wi)
    smooth = brdf.OrenNayarParams(albedo, _t(0.0, device=device))
    torch.testing.assert_close(brdf.oren_nayar.eval(smooth, wo, wi), lambert)
    # Opposite azimuths: only the A term is left.
    opposite = _direction(30.0, math.pi, device)
    torch.testing.assert_close(brdf.oren_nayar.eval(params, wo, opposite), albedo * 0.7844827586206897 / math.pi)


@pytest.mark.parametrize("k", [0.5, 1.0, 2.5])
def test_minnaert_albedo_closed_form(device, k):
    # albedo(theta_o) = rho cos(theta_o)^(k - 1): above rho at grazing for the velvet range k < 1.
    params = brdf.MinnaertParams(_t(1.0, 1.0, 1.0, device=device), _t(k, device=device))
    for theta in (0.0, 45.0, 80.0):
        expected = math.cos(math.radians(theta)) ** (k - 1)
        albedo = _albedo(brdf.minnaert, params, _direction(theta, device=device))
        assert float(albedo[0]) == pytest.approx(expected, rel=1e-4)


def test_ward_peak_by_hand(device, tolerances):
    # wo = wi = n, isotropic 0.2: h = (0, 0, 2), exponent 0 -> rho / (4 pi a^2).
    params = brdf.WardParams(_t(0.9, 0.6, 0.3, device=device), _t(0.2, device=device), _t(0.2, device=device))
    torch.testing.assert_close(
        brdf.ward.eval(params, NORMAL.to(device), NORMAL.to(device)),
        _t(0.9, 0.6, 0.3, device=device) * 1.9894367886486917,
        **tolerances[DTYPE],
    )


def test_ward_anisotropy_follows_the_tangent(device):
    # Narrow along x (alpha_x small): tilting the pair of directions along x falls off faster.
    params = brdf.WardParams(_t(1.0, 1.0, 1.0, device=device), _t(0.1, device=device), _t(0.4, device=device))
    wo = _direction(20.0, 0.0, device)
    along_x = brdf.ward.eval(params, wo, _direction(40.0, math.pi, device))
    wo_y = _direction(20.0, math.pi / 2, device)
    along_y = brdf.ward.eval(params, wo_y, _direction(40.0, -math.pi / 2, device))
    assert float(along_x[0, 0]) < float(along_y[0, 0])


GRADCHECK_CASES = {
    "lambert": (brdf.lambert, lambda albedo, scalar: brdf.LambertParams(albedo)),
    "oren_nayar": (brdf.oren_nayar, lambda albedo, scalar: brdf.OrenNayarParams(albedo, scalar)),
    "cook_torrance": (brdf.cook_torrance, lambda albedo, scalar: brdf.CookTorranceParams(albedo, scalar)),
    "ward": (brdf.ward, lambda albedo, scalar: brdf.WardParams(albedo, scalar, scalar * 1.7)),
    "phong": (brdf.phong, lambda albedo, scalar: brdf.PhongParams(albedo, scalar * 20)),
    "preview_surface": (
        brdf.preview_surface,
        lambda albedo, scalar: brdf.PreviewSurfaceParams(
            albedo,
            albedo * 0,
            albedo * 0.5,
            scalar,
            scalar + 0.2,
            scalar,
            scalar,
            scalar + 1.2,
            scalar * 0 + 1,
            torch.tensor([False, True, False, True], device=albedo.device),
        ),
    ),
}


@pytest.mark.parametrize("name", list(GRADCHECK_CASES))
def test_gradcheck_float64(name, device):
    module, build = GRADCHECK_CASES[name]
    generator = torch.Generator().manual_seed(31)
    albedo = torch.rand(4, 3, generator=generator, dtype=DTYPE).to(device).requires_grad_()
    scalar = (0.2 + 0.5 * torch.rand(4, generator=generator, dtype=DTYPE)).to(device).requires_grad_()
    # Directions near the mirror configuration and away from the kinks (max, clamps).
    wo = torch.tensor([[0.3, 0.2, 0.9], [0.5, -0.1, 0.7], [-0.2, 0.4, 0.8], [0.1, 0.1, 1.0]], dtype=DTYPE)
    wo = torch.nn.functional.normalize(wo, dim=-1)
    wi = torch.nn.functional.normalize(wo * torch.tensor([-1.0, -1.0, 1.0], dtype=DTYPE) + 0.05, dim=-1)
    wo, wi = wo.to(device).requires_grad_(), wi.to(device).requires_grad_()

    def function(albedo, scalar, wo, wi):
        return module.eval(build(albedo, scalar), wo, wi)

    assert torch.autograd.gradcheck(function, (albedo, scalar, wo, wi))


def test_directions_and_params_are_checked():
    params = brdf.LambertParams(_t(0.5, 0.5, 0.5))
    with pytest.raises(ValueError, match=r"wi_local must have shape \(\.\.\., 3\); got \(4, 2\)"):
        brdf.lambert.eval(params, torch.ones(4, 3, dtype=DTYPE), torch.ones(4, 2, dtype=DTYPE))
    with pytest.raises(ValueError, match=r"u must have shape"):
        brdf.lambert.sample(params, torch.ones(4, 3, dtype=DTYPE), torch.ones(4, 3, dtype=DTYPE))
    with pytest.raises(ValueError, match=r"LambertParams.albedo must have shape \(N, 3\); got \(2, 4\)"):
        brdf.LambertParams(torch.ones(2, 4))
    with pytest.raises(ValueError, match=r"PhongParams.exponent has rows \(3,\); the fields before it have \(2,\)"):
        brdf.PhongParams(torch.ones(2, 3), torch.ones(3))
    with pytest.raises(ValueError, match=r"must be a torch\.Tensor"):
        brdf.PhongParams([[1.0, 1.0, 1.0]], torch.ones(1))
