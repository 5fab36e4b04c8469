"""UsdPreviewSurface against Storm's previewSurface.glslfx: hand values, a line-by-line scalar
transcription of `evaluateLight` (the slow twin), the diffuse/specular split, energy facts,
sampling weights and the params container."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from relight_torch.brdf import preview_surface
from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.math.sampling import hemisphere_quadrature

DTYPE = torch.float64
NORMAL = torch.tensor([[0.0, 0.0, 1.0]], dtype=DTYPE)


def _params(
    diffuse=(0.5, 0.5, 0.5),
    specular=(0.0, 0.0, 0.0),
    metallic=0.0,
    roughness=0.5,
    clearcoat=0.0,
    clearcoat_roughness=0.01,
    ior=1.5,
    specular_workflow=False,
) -> PreviewSurfaceParams:
    return PreviewSurfaceParams(
        diffuse_color=torch.tensor([diffuse], dtype=DTYPE),
        emissive_color=torch.tensor([[0.3, 0.2, 0.1]], dtype=DTYPE),
        specular_color=torch.tensor([specular], dtype=DTYPE),
        metallic=torch.tensor([metallic], dtype=DTYPE),
        roughness=torch.tensor([roughness], dtype=DTYPE),
        clearcoat=torch.tensor([clearcoat], dtype=DTYPE),
        clearcoat_roughness=torch.tensor([clearcoat_roughness], dtype=DTYPE),
        ior=torch.tensor([ior], dtype=DTYPE),
        opacity=torch.tensor([0.25], dtype=DTYPE),
        use_specular_workflow=torch.tensor([specular_workflow]),
    )


def test_specular_workflow_at_normal_incidence_by_hand(tolerances):
    # roughness 0.5: a = 0.25, a^2 = 0.0625; D = 1/(pi 0.0625) = 5.092958178940651 (exact GGX);
    # G = 1; fres = 0 so F = F0; spec = F0 D / (4 + 0.001) = F0 * 1.272921314406561.
    # diffuse = 0.5/pi (1 - F0). Opacity (0.25) and emission are not part of the BRDF.
    params = _params(specular=(0.04, 0.5, 1.0), specular_workflow=True)
    diffuse, specular = preview_surface.split(params, NORMAL, NORMAL)
    expected_specular = torch.tensor([[0.05091685257626244, 0.6364606572032805, 1.272921314406561]], dtype=DTYPE)
    expected_diffuse = torch.tensor([[0.15278874536821951, 0.07957747154594767, 0.0]], dtype=DTYPE)
    torch.testing.assert_close(specular, expected_specular, **tolerances[DTYPE])
    torch.testing.assert_close(diffuse, expected_diffuse, **tolerances[DTYPE])
    torch.testing.assert_close(preview_surface.eval(params, NORMAL, NORMAL), expected_specular + expected_diffuse)


def test_metal_at_normal_incidence_by_hand(tolerances):
    # metallic 1: F0 = F90 = diffuseColor, no diffuse; spec = diffuseColor * 1.272921314406561.
    params = _params(diffuse=(0.9, 0.6, 0.2), metallic=1.0)
    diffuse, specular = preview_surface.split(params, NORMAL, NORMAL)
    torch.testing.assert_close(
        specular, torch.tensor([[1.1456291829659049, 0.7637527886439366, 0.2545842628813122]], dtype=DTYPE)
    )
    assert torch.all(diffuse == 0)


def test_clearcoat_at_normal_incidence_by_hand(tolerances):
    # ior 1.5: R^2 = 0.04; clearcoatRoughness 0.1: a = 0.01, D = 1/(pi 1e-4) = 3183.098861837907;
    # coat = 0.04 D / 4.001 = 31.823032860164027, added on top of a black specular-workflow base.
    params = _params(diffuse=(0.0, 0.0, 0.0), clearcoat=1.0, clearcoat_roughness=0.1, specular_workflow=True)
    torch.testing.assert_close(
        preview_surface.eval(params, NORMAL, NORMAL),
        torch.full((1, 3), 31.823032860164027, dtype=DTYPE),
        **tolerances[DTYPE],
    )


def _storm_evaluate_light(p: dict, n_dot_l: float, n_dot_e: float, n_dot_h: float, e_dot_h: float) -> tuple:
    """previewSurface.glslfx `evaluateLight` transcribed statement by statement (floats, RGB
    tuples), with occlusion 1 and unit light irradiances; returns (diffuse, specular) / NdotL.

    One line differs from Storm, as in preview_surface.py: the NDF numerator is alpha^2, not
    alpha^2 + epsilon (the exact GGX)."""
    epsilon = 0.001

    def mix(x, y, a):
        return (
            tuple(xi * (1 - a) + yi * a for xi, yi in zip(x, y, strict=True))
            if isinstance(a, float)
            else tuple(xi * (1 - ai) + yi * ai for xi, yi, ai in zip(x, y, a, strict=True))
        )

    def normal_distribution(roughness, ndoth):
        alpha = roughness * roughness
        alpha2 = alpha * alpha
        ddenom = (ndoth * ndoth * (alpha2 - 1.0)) + 1.0
        return alpha2 / (ddenom * ddenom * math.pi)

    def geometric(roughness, ndotl, ndote):
        k = roughness * roughness * 0.5
        return ndote / (ndote * (1.0 - k) + k) * ndotl / (ndotl * (1.0 - k) + k)

    def direct_specular(f0, f90, roughness, fresnel):
        f = mix(f0, f90, fresnel)
        d = normal_distribution(roughness, n_dot_h)
        g = geometric(roughness, n_dot_l, n_dot_e)
        return tuple(fi * g * d / (4.0 * n_dot_l * n_dot_e + epsilon) for fi in f)

    specular_roughness = max(0.001, p["roughness"])
    clearcoat_roughness = max(0.001, p["clearcoat_roughness"])
    fresnel = max(0.0, 1.0 - e_dot_h) ** 5
    d = tuple(c / math.pi for c in p["diffuse_color"])
    r = (1.0 - p["ior"]) / (1.0 + p["ior"])
    f0, f90 = p["specular_color"], (1.0, 1.0, 1.0)
    if not p["use_specular_workflow"]:
        spec_color = mix((1.0, 1.0, 1.0), p["diffuse_color"], p["metallic"])
        f0 = mix(tuple(r * r * c for c in spec_color), spec_color, p["metallic"])
        f90 = spec_color
        d = tuple(c * (1.0 - p["metallic"]) for c in d)
    s1 = direct_specular(f0, f90, specular_roughness, fresnel)
    d = tuple(di * (1.0 - fi) for di, fi in zip(d, mix(f0, f90, fresnel), strict=True))
    s2 = tuple(p["clearcoat"] * c for c in direct_specular((r * r,) * 3, (1.0, 1.0, 1.0), clearcoat_roughness, fresnel))
    return d, tuple(a + b for a, b in zip(s1, s2, strict=True))


def test_matches_a_scalar_transcription_of_storm(tolerances):
    generator = np.random.default_rng(41)
    num_points = 64
    arrays = {
        "diffuse_color": generator.uniform(0, 1, (num_points, 3)),
        "emissive_color": generator.uniform(0, 1, (num_points, 3)),
        "specular_color": generator.uniform(0, 1, (num_points, 3)),
        "metallic": generator.uniform(0, 1, num_points),
        "roughness": np.concatenate((generator.uniform(0, 1, num_points - 2), [0.0, 0.0005])),
        "clearcoat": generator.uniform(0, 1, num_points),
        "clearcoat_roughness": generator.uniform(0.0, 1, num_points),
        "ior": generator.uniform(1.0, 2.5, num_points),
        "opacity": generator.uniform(0, 1, num_points),
        "use_specular_workflow": generator.uniform(0, 1, num_points) < 0.5,
    }
    params = PreviewSurfaceParams.from_numpy(arrays, dtype=DTYPE)
    wo = torch.nn.functional.normalize(torch.from_numpy(generator.normal(size=(num_points, 3))), dim=-1)
    wi = torch.nn.functional.normalize(torch.from_numpy(generator.normal(size=(num_points, 3))), dim=-1)
    wo, wi = wo * wo[:, 2:].sign(), wi * wi[:, 2:].sign()
    diffuse, specular = preview_surface.split(params, wo, wi)
    for i in range(num_points):
        h = torch.nn.functional.normalize(wo[i] + wi[i], dim=0)
        row = {key: (tuple(value[i]) if np.ndim(value) == 2 else value[i].item()) for key, value in arrays.items()}
        expected_diffuse, expected_specular = _storm_evaluate_light(
            row, float(wi[i, 2]), float(wo[i, 2]), max(0.0, float(h[2])), max(0.0, float(wo[i] @ h))
        )
        torch.testing.assert_close(diffuse[i], torch.tensor(expected_diffuse, dtype=DTYPE), rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(specular[i], torch.tensor(expected_specular, dtype=DTYPE), rtol=1e-9, atol=1e-12)


def test_diffuse_albedo_follows_the_workflow():
    metallic = _params(diffuse=(0.8, 0.4, 0.2), metallic=0.25)
    specular = _params(diffuse=(0.8, 0.4, 0.2), metallic=0.25, specular_workflow=True)
    assert preview_surface.diffuse_albedo(metallic)[0].tolist() == pytest.approx([0.6, 0.3, 0.15])
    assert preview_surface.diffuse_albedo(specular)[0].tolist() == pytest.approx([0.8, 0.4, 0.2])


def _albedo(params: PreviewSurfaceParams, theta_deg: float, num_theta: int = 512, num_phi: int = 128) -> float:
    """Directional albedo (red channel) at theta_o by midpoint quadrature."""
    wi, weights = hemisphere_quadrature(num_theta, num_phi, dtype=DTYPE)
    theta = math.radians(theta_deg)
    wo = torch.tensor([math.sin(theta), 0.0, math.cos(theta)], dtype=DTYPE).expand_as(wi)
    return float((preview_surface.eval(params, wo, wi)[:, 0] * wi[:, 2] * weights).sum())


def test_exact_ggx_conserves_energy_at_low_roughness():
    # Storm's NDF numerator (a^2 + 0.001) would make a white metal at roughness 0.2 reflect ~1.62 at
    # normal incidence (the lobe scaled by 1.63); with the exact GGX we use it stays just below 1.
    # (At normal incidence the integrand does not depend on phi: few phi cells, many theta cells.)
    for roughness, num_theta in ((0.2, 4096), (0.05, 8192)):
        albedo = _albedo(
            _params(diffuse=(1, 1, 1), metallic=1.0, roughness=roughness), 0.0, num_theta=num_theta, num_phi=4
        )
        assert 0.99 < albedo <= 1.0


def test_white_furnace_where_storm_conserves_energy():
    # Measured regime: white metal at roughness >= 0.5 and white dielectric at roughness 1.
    for theta in (0.0, 45.0, 75.0, 89.0):
        assert _albedo(_params(diffuse=(1, 1, 1), metallic=1.0, roughness=0.5), theta) <= 1.0
        assert _albedo(_params(diffuse=(1, 1, 1), roughness=1.0), theta) <= 1.0
    # ...and not near grazing for a white dielectric at roughness 0.5 (diffuse (1 - F(h)) + spec).
    assert _albedo(_params(diffuse=(1, 1, 1), roughness=0.5), 89.0) > 1.05


def test_lobe_probabilities():
    wo = torch.tensor([[0.0, 0.0, 1.0]], dtype=DTYPE)
    # Black specular workflow without coat: only the diffuse lobe.
    only_diffuse = preview_surface.lobe_probabilities(_params(specular_workflow=True), wo)
    assert only_diffuse.tolist() == [[1.0, 0.0, 0.0]]
    # Metal: F = diffuse colour at normal incidence, no diffuse, and no coat.
    metal = preview_surface.lobe_probabilities(_params(diffuse=(0.9, 0.6, 0.3), metallic=1.0), wo)
    assert metal.tolist() == [[0.0, 1.0, 0.0]]
    # A black material still samples something.
    black = preview_surface.lobe_probabilities(_params(diffuse=(0, 0, 0), specular_workflow=True), wo)
    assert black.tolist() == [[1.0, 0.0, 0.0]]
    mixed = preview_surface.lobe_probabilities(_params(clearcoat=1.0), wo)
    assert float(mixed.sum()) == pytest.approx(1.0) and torch.all(mixed > 0)


def test_params_container_round_trip():
    arrays = {
        "diffuse_color": np.full((3, 3), 0.18, np.float32),
        "emissive_color": np.zeros((3, 3), np.float32),
        "specular_color": np.zeros((3, 3), np.float32),
        "metallic": np.array([0.0, 0.5, 1.0], np.float32),
        "roughness": np.full(3, 0.5, np.float32),
        "clearcoat": np.zeros(3, np.float32),
        "clearcoat_roughness": np.full(3, 0.01, np.float32),
        "ior": np.full(3, 1.5, np.float32),
        "opacity": np.ones(3, np.float32),
        "use_specular_workflow": np.array([0, 1, 0], np.int32),
        "normal_tangent": np.zeros((3, 3), np.float32),
    }
    params = PreviewSurfaceParams.from_numpy(arrays)
    assert params.metallic.dtype == torch.float32 and params.use_specular_workflow.dtype == torch.bool
    as_double = params.to(dtype=torch.float64)
    assert as_double.roughness.dtype == torch.float64 and as_double.use_specular_workflow.dtype == torch.bool
    picked = params.index(torch.tensor([False, True, True]))
    assert picked.metallic.tolist() == [0.5, 1.0] and picked.use_specular_workflow.tolist() == [True, False]
    with pytest.raises(ValueError, match="missing array 'ior'"):
        PreviewSurfaceParams.from_numpy({k: v for k, v in arrays.items() if k != "ior"})
    with pytest.raises(AttributeError):
        params.metallic = params.roughness


def test_clearcoat_at_its_default_roughness_reflects_its_fresnel():
    # Clearcoat 1 at the USD fallback clearcoatRoughness 0.01 (a^2 = 1e-8): with the exact GGX the
    # directional albedo at normal incidence is R^2 * 4/4.001 = 0.03999 (G ~ 1, fres ~ 0 for so
    # narrow a lobe); Storm's (a^2 + 0.001) numerator would make it 3999. Importance sampling with
    # the exact GGX keeps the estimate almost noise-free.
    params = _params(diffuse=(0, 0, 0), clearcoat=1.0, clearcoat_roughness=0.01, specular_workflow=True)
    num_samples = 4096
    wo = NORMAL.expand(num_samples, 3)
    u = torch.rand(num_samples, 2, generator=torch.Generator().manual_seed(43), dtype=DTYPE)
    wi, density = preview_surface.sample(params, wo, u)
    weight = preview_surface.eval(params, wo, wi)[:, 0] * wi[:, 2] / density
    standard_error = float(weight.std()) / math.sqrt(num_samples)
    assert float(weight.mean()) == pytest.approx(0.03999, abs=4 * standard_error + 5e-4)
