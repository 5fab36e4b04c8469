"""Physics properties every BRDF must have, parametrised over all of them.

Monte Carlo comparisons use the measured standard error of the estimates (4 sigma); quadrature
comparisons use a fine midpoint grid. Random numbers are seeded; the tests are deterministic.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from types import ModuleType, SimpleNamespace

import pytest
import scipy.stats
import torch

from relight_torch import brdf
from relight_torch.brdf.params import BrdfParams
from relight_torch.math.sampling import hemisphere_quadrature, uniform_hemisphere

DTYPE = torch.float64
WO_THETAS_DEG = (0.0, 30.0, 60.0, 80.0)
WO_PHI = 0.7  # off the tangent axis, so that Ward's anisotropy matters


def _rows(device, dtype, *values) -> torch.Tensor:
    return (
        torch.tensor([values], device=device, dtype=dtype)
        if len(values) == 3
        else torch.tensor(values, device=device, dtype=dtype)
    )


def _preview(device, dtype, specular_workflow: bool) -> brdf.PreviewSurfaceParams:
    return brdf.PreviewSurfaceParams(
        diffuse_color=_rows(device, dtype, 0.5, 0.4, 0.3),
        emissive_color=_rows(device, dtype, 0.0, 0.0, 0.0),
        specular_color=_rows(device, dtype, 0.3, 0.25, 0.2),
        metallic=_rows(device, dtype, 0.3),
        roughness=_rows(device, dtype, 0.5),
        clearcoat=_rows(device, dtype, 0.6),
        clearcoat_roughness=_rows(device, dtype, 0.35),
        ior=_rows(device, dtype, 1.5),
        opacity=_rows(device, dtype, 1.0),
        use_specular_workflow=torch.tensor([specular_workflow], device=device),
    )


ParamsBuilder = Callable[[torch.device, torch.dtype], BrdfParams]

# UsdPreviewSurface's specular and clearcoat part alone (`split`'s second value) with its own
# sampler (`sample(..., diffuse=False)`), which the transfer bake's glossy rows draw from.
PREVIEW_SPECULAR_LOBES = SimpleNamespace(
    eval=lambda params, wo, wi: brdf.preview_surface.split(params, wo, wi)[1],
    sample=functools.partial(brdf.preview_surface.sample, diffuse=False),
    pdf=functools.partial(brdf.preview_surface.pdf, diffuse=False),
)

# One moderate, coloured parameter set per model (and both Storm workflows).
CASES: dict[str, tuple[ModuleType | SimpleNamespace, ParamsBuilder]] = {
    "lambert": (brdf.lambert, lambda d, t: brdf.LambertParams(_rows(d, t, 0.8, 0.5, 0.2))),
    "phong": (brdf.phong, lambda d, t: brdf.PhongParams(_rows(d, t, 0.9, 0.7, 0.5), _rows(d, t, 12.0))),
    "blinn_phong": (
        brdf.blinn_phong,
        lambda d, t: brdf.BlinnPhongParams(_rows(d, t, 0.9, 0.7, 0.5), _rows(d, t, 20.0)),
    ),
    "cook_torrance": (
        brdf.cook_torrance,
        lambda d, t: brdf.CookTorranceParams(_rows(d, t, 0.9, 0.6, 0.3), _rows(d, t, 0.3)),
    ),
    "oren_nayar": (brdf.oren_nayar, lambda d, t: brdf.OrenNayarParams(_rows(d, t, 0.8, 0.5, 0.2), _rows(d, t, 0.6))),
    "minnaert": (brdf.minnaert, lambda d, t: brdf.MinnaertParams(_rows(d, t, 0.8, 0.5, 0.2), _rows(d, t, 1.6))),
    "ward": (
        brdf.ward,
        lambda d, t: brdf.WardParams(_rows(d, t, 0.9, 0.6, 0.3), _rows(d, t, 0.15), _rows(d, t, 0.4)),
    ),
    "preview_metallic": (brdf.preview_surface, lambda d, t: _preview(d, t, specular_workflow=False)),
    "preview_specular": (brdf.preview_surface, lambda d, t: _preview(d, t, specular_workflow=True)),
    "preview_specular_lobes": (PREVIEW_SPECULAR_LOBES, lambda d, t: _preview(d, t, specular_workflow=False)),
}

# White parameters of the models (and parameter ranges) claimed to conserve energy.
WHITE_CASES: dict[str, tuple[ModuleType, ParamsBuilder]] = {
    **{
        f"oren_nayar_sigma{s}": (
            brdf.oren_nayar,
            lambda d, t, s=s: brdf.OrenNayarParams(_rows(d, t, 1, 1, 1), _rows(d, t, s)),
        )
        for s in (0.3, 1.0)
    },
    **{
        f"phong_n{n}": (brdf.phong, lambda d, t, n=n: brdf.PhongParams(_rows(d, t, 1, 1, 1), _rows(d, t, n)))
        for n in (1.0, 30.0)
    },
    **{
        f"blinn_phong_n{n}": (
            brdf.blinn_phong,
            lambda d, t, n=n: brdf.BlinnPhongParams(_rows(d, t, 1, 1, 1), _rows(d, t, n)),
        )
        for n in (0.0, 1.0, 10.0, 100.0)
    },
    **{
        f"cook_torrance_alpha{a}": (
            brdf.cook_torrance,
            lambda d, t, a=a: brdf.CookTorranceParams(_rows(d, t, 1, 1, 1), _rows(d, t, a)),
        )
        for a in (0.05, 0.3, 1.0)
    },
    **{
        f"ward_{ax}_{ay}": (
            brdf.ward,
            lambda d, t, ax=ax, ay=ay: brdf.WardParams(_rows(d, t, 1, 1, 1), _rows(d, t, ax), _rows(d, t, ay)),
        )
        for ax, ay in ((0.05, 0.05), (0.1, 0.4), (0.8, 0.8))
    },
    **{
        f"minnaert_k{k}": (brdf.minnaert, lambda d, t, k=k: brdf.MinnaertParams(_rows(d, t, 1, 1, 1), _rows(d, t, k)))
        for k in (1.0, 2.5)
    },
}


def _wo_grid(device, thetas_deg=WO_THETAS_DEG) -> torch.Tensor:
    theta = torch.tensor(thetas_deg, dtype=DTYPE, device=device).deg2rad()
    return torch.stack(
        (torch.sin(theta) * math.cos(WO_PHI), torch.sin(theta) * math.sin(WO_PHI), torch.cos(theta)), dim=-1
    )


def _uniform(shape: tuple[int, ...], seed: int, device) -> torch.Tensor:
    return torch.rand(*shape, 2, generator=torch.Generator().manual_seed(seed), dtype=DTYPE).to(device)


def _mean_and_error(values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean over axis 1 of (M, S, C) estimates and its standard error."""
    return values.mean(1), values.std(1) / math.sqrt(values.shape[1])


def _importance_estimate(module, params, wo: torch.Tensor, num_samples: int, seed: int):
    """Directional albedo estimate (M, 3) +- error by the BRDF's own sampler."""
    wo_samples = wo[:, None, :].expand(-1, num_samples, -1)
    wi, pdf = module.sample(params.with_sample_axis(), wo_samples, _uniform(wo_samples.shape[:-1], seed, wo.device))
    value = module.eval(params.with_sample_axis(), wo_samples, wi) * wi[..., 2:3]
    weight = torch.where(pdf[..., None] > 0, value / pdf.clamp_min(1e-300)[..., None], 0.0)
    return _mean_and_error(weight)


def _uniform_estimate(module, params, wo: torch.Tensor, num_samples: int, seed: int):
    """Directional albedo estimate (M, 3) +- error with uniform hemisphere directions."""
    wi, pdf = uniform_hemisphere(_uniform((wo.shape[0], num_samples), seed, wo.device))
    wo_samples = wo[:, None, :].expand_as(wi)
    value = module.eval(params.with_sample_axis(), wo_samples, wi) * wi[..., 2:3] / pdf[..., None]
    return _mean_and_error(value)


@pytest.fixture(params=list(CASES), ids=list(CASES))
def case(request):
    return CASES[request.param]


def test_non_negative_finite_and_zero_below_horizon(case, device):
    module, build = case
    params = build(device, DTYPE)
    generator = torch.Generator().manual_seed(11)
    wo = torch.nn.functional.normalize(torch.randn(20000, 3, generator=generator, dtype=DTYPE), dim=-1).to(device)
    wi = torch.nn.functional.normalize(torch.randn(20000, 3, generator=generator, dtype=DTYPE), dim=-1).to(device)
    value = module.eval(params, wo, wi)
    density = module.pdf(params, wo, wi)
    assert value.shape == (20000, 3) and density.shape == (20000,)
    assert torch.all(torch.isfinite(value)) and torch.all(value >= 0)
    assert torch.all(torch.isfinite(density)) and torch.all(density >= 0)
    below = (wo[:, 2] <= 0) | (wi[:, 2] <= 0)
    assert torch.all(value[below] == 0) and torch.all(density[below] == 0)


def test_helmholtz_reciprocity(case, device, tolerances):
    # Every model here is reciprocal, Storm's previewSurface included (E.h = L.h in its F).
    module, build = case
    params = build(device, DTYPE)
    generator = torch.Generator().manual_seed(12)
    wo = torch.nn.functional.normalize(torch.randn(5000, 3, generator=generator, dtype=DTYPE), dim=-1).to(device)
    wi = torch.nn.functional.normalize(torch.randn(5000, 3, generator=generator, dtype=DTYPE), dim=-1).to(device)
    wo, wi = wo * wo[:, 2:].sign(), wi * wi[:, 2:].sign()
    torch.testing.assert_close(module.eval(params, wo, wi), module.eval(params, wi, wo), **tolerances[DTYPE])


def test_sample_returns_unit_directions_and_their_pdf(case, device, tolerances):
    module, build = case
    params = build(device, DTYPE)
    wo = _wo_grid(device)[:, None, :].expand(-1, 2048, -1)
    wi, density = module.sample(params.with_sample_axis(), wo, _uniform(wo.shape[:-1], 13, device))
    assert wi.shape == wo.shape and density.shape == wo.shape[:-1]
    torch.testing.assert_close(wi.norm(dim=-1), torch.ones_like(density), **tolerances[DTYPE])
    torch.testing.assert_close(density, module.pdf(params.with_sample_axis(), wo, wi), **tolerances[DTYPE])
    assert torch.all(wi[density > 0][:, 2] > 0)
    # A viewer below the surface gets only lost samples.
    below = -_wo_grid(device)[:, None, :].expand(-1, 16, -1)
    assert torch.all(module.sample(params.with_sample_axis(), below, _uniform(below.shape[:-1], 14, device))[1] == 0)


def test_pdf_integrates_to_the_fraction_of_kept_samples(case, device):
    module, build = case
    params = build(device, DTYPE)
    wo = _wo_grid(device)
    grid, weights = hemisphere_quadrature(256, 256, device=device, dtype=DTYPE)
    wo_grid = wo[:, None, :].expand(-1, grid.shape[0], -1)
    integral = (module.pdf(params.with_sample_axis(), wo_grid, grid.expand_as(wo_grid)) * weights).sum(-1)
    num_samples = 1 << 15
    wo_samples = wo[:, None, :].expand(-1, num_samples, -1)
    _, density = module.sample(params.with_sample_axis(), wo_samples, _uniform(wo_samples.shape[:-1], 15, device))
    kept = (density > 0).to(DTYPE).mean(-1)
    binomial_error = torch.sqrt(kept * (1 - kept) / num_samples)
    quadrature_error = 2e-3
    assert torch.all(integral <= 1 + quadrature_error)
    assert torch.all((integral - kept).abs() <= 4 * binomial_error + quadrature_error), (integral, kept)
    # Where the sampler loses nothing (cosine-like samplers), this says the pdf integrates to 1.
    if module in (brdf.lambert, brdf.oren_nayar, brdf.minnaert):
        assert torch.all(kept == 1)


def test_importance_sampling_agrees_with_uniform_sampling(case, device):
    module, build = case
    params = build(device, DTYPE)
    wo = _wo_grid(device)
    importance, importance_error = _importance_estimate(module, params, wo, 1 << 15, seed=16)
    uniform, uniform_error = _uniform_estimate(module, params, wo, 1 << 17, seed=17)
    bound = 4 * torch.sqrt(importance_error**2 + uniform_error**2)
    assert torch.all((importance - uniform).abs() <= bound), (importance, uniform, bound)


@pytest.mark.parametrize("name", list(WHITE_CASES))
def test_white_furnace(name, device):
    module, build = WHITE_CASES[name]
    params = build(device, DTYPE)
    wo = _wo_grid(device, thetas_deg=(0.0, 20.0, 45.0, 60.0, 75.0, 85.0, 89.0))
    albedo, error = _importance_estimate(module, params, wo, 1 << 14, seed=18)
    assert torch.all(albedo <= 1 + 4 * error + 1e-9), (albedo, error)


def test_lambert_furnace_is_exactly_one(device):
    params = brdf.LambertParams(_rows(device, DTYPE, 1, 1, 1))
    albedo, error = _importance_estimate(brdf.lambert, params, _wo_grid(device), 256, seed=19)
    torch.testing.assert_close(albedo, torch.ones_like(albedo))
    assert torch.all(error < 1e-12)


def _chi_square_p_value(module, params, wo: torch.Tensor, num_samples: int, seed: int) -> float:
    """p-value of the sampler's (theta, phi) histogram against the integrated pdf.

    Bins: 16 x 32 over the hemisphere plus one bin of lost samples; bins expecting fewer than 5
    samples are pooled.
    """
    num_theta, num_phi, refine = 16, 32, 8
    wo_samples = wo.expand(num_samples, 3)
    wi, density = module.sample(params, wo_samples, _uniform((num_samples,), seed, wo.device))
    kept = density > 0
    theta = torch.acos(wi[kept][:, 2].clamp(-1, 1))
    phi = torch.atan2(wi[kept][:, 1], wi[kept][:, 0]) % (2 * math.pi)
    theta_bin = (theta / (0.5 * math.pi) * num_theta).long().clamp_max(num_theta - 1)
    phi_bin = (phi / (2 * math.pi) * num_phi).long().clamp_max(num_phi - 1)
    observed = torch.bincount(theta_bin * num_phi + phi_bin, minlength=num_theta * num_phi).to(DTYPE)
    grid, weights = hemisphere_quadrature(num_theta * refine, num_phi * refine, device=wo.device, dtype=DTYPE)
    fine = (module.pdf(params, wo.expand_as(grid), grid) * weights).reshape(num_theta, refine, num_phi, refine)
    expected = fine.sum((1, 3)).reshape(-1) * num_samples
    observed = torch.cat((observed, (~kept).sum().to(DTYPE).reshape(1)))
    expected = torch.cat((expected, (num_samples - expected.sum()).clamp_min(0).reshape(1)))
    small = expected < 5
    observed = torch.cat((observed[~small], observed[small].sum().reshape(1)))
    expected = torch.cat((expected[~small], expected[small].sum().reshape(1)))
    nonempty = expected > 0
    statistic = float((((observed - expected) ** 2)[nonempty] / expected[nonempty]).sum())
    return float(scipy.stats.chi2.sf(statistic, int(nonempty.sum()) - 1))


@pytest.mark.parametrize("theta_o_deg", [10.0, 55.0])
def test_sampler_chi_square(case, device, theta_o_deg):
    module, build = case
    params = build(device, DTYPE)
    wo = _wo_grid(device, thetas_deg=(theta_o_deg,))
    assert _chi_square_p_value(module, params, wo, 1 << 17, seed=20) > 1e-3


def test_sampler_chi_square_rejects_a_wrong_pdf(device):
    # Power check: the cosine sampler tested against the pdf of a slightly different lobe fails.
    class Biased:
        sample = staticmethod(brdf.minnaert.sample)

        @staticmethod
        def pdf(params, wo, wi):
            return brdf.minnaert.pdf(brdf.MinnaertParams(params.albedo, params.k * 1.1), wo, wi)

    params = brdf.MinnaertParams(_rows(device, DTYPE, 1, 1, 1), _rows(device, DTYPE, 1.0))
    assert _chi_square_p_value(Biased, params, _wo_grid(device, (30.0,)), 1 << 17, seed=21) < 1e-6


def test_rows_broadcast_against_sample_axis(case, device, tolerances):
    module, build = case
    one_row = build(device, DTYPE)
    three_rows = one_row.index(torch.tensor([0, 0, 0], device=device))
    wo = _wo_grid(device, (10.0, 40.0, 70.0))
    wo_samples = wo[:, None, :].expand(-1, 64, -1)
    wi, _ = module.sample(three_rows.with_sample_axis(), wo_samples, _uniform((3, 64), 22, device))
    batched = module.eval(three_rows.with_sample_axis(), wo[:, None, :].expand_as(wi), wi)
    for row in range(3):
        single = module.eval(one_row, wo[row].expand(64, 3), wi[row])
        torch.testing.assert_close(batched[row], single, **tolerances[DTYPE])


def test_float32_and_float64_agree_on_device(case, device):
    module, build = case
    generator = torch.Generator().manual_seed(23)
    wo = torch.nn.functional.normalize(torch.rand(512, 3, generator=generator, dtype=DTYPE) + 0.05, dim=-1)
    wi = torch.nn.functional.normalize(torch.rand(512, 3, generator=generator, dtype=DTYPE) - 0.5, dim=-1)
    wi = wi * wi[:, 2:].sign()
    results = {}
    for dtype in (torch.float32, torch.float64):
        params = build(torch.device("cpu"), torch.float64).to(device, dtype)
        value = module.eval(params, wo.to(device, dtype), wi.to(device, dtype))
        density = module.pdf(params, wo.to(device, dtype), wi.to(device, dtype))
        assert value.dtype == dtype and density.dtype == dtype and value.device.type == device.type
        results[dtype] = (value.double().cpu(), density.double().cpu())
    for low, high in zip(results[torch.float32], results[torch.float64], strict=True):
        torch.testing.assert_close(low, high, rtol=2e-4, atol=1e-6)
