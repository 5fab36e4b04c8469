"""BRDFs as sums of coloured primitive terms (relight_torch.brdf.terms)."""

from __future__ import annotations

import importlib

import pytest
import torch

from relight_torch import brdf
from relight_torch.brdf.terms import TERM_MODULES, BrdfTerm, eval_terms, term_module

DTYPE = torch.float64


def _directions(num: int, seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    w = torch.nn.functional.normalize(torch.randn(num, 3, generator=generator, dtype=DTYPE), dim=-1)
    return w * w[:, 2:].sign()


def test_registry_names_every_brdf_module():
    assert set(TERM_MODULES) == {
        "lambert",
        "phong",
        "blinn_phong",
        "cook_torrance",
        "oren_nayar",
        "minnaert",
        "ward",
        "preview_surface",
    }
    for name, module in TERM_MODULES.items():
        assert module is importlib.import_module(f"relight_torch.brdf.{name}")
        assert all(callable(getattr(module, f)) for f in ("eval", "sample", "pdf"))


def test_sum_of_coloured_terms(tolerances):
    num = 64
    wo, wi = _directions(num, 1), _directions(num, 2)
    ones = torch.ones(num, dtype=DTYPE)
    white = torch.ones(num, 3, dtype=DTYPE)
    diffuse_colour = torch.rand(num, 3, generator=torch.Generator().manual_seed(3), dtype=DTYPE)
    specular_colour = torch.full((num, 3), 0.25, dtype=DTYPE)
    lambert_params = brdf.LambertParams(white)
    phong_params = brdf.PhongParams(white, 30 * ones)
    terms = [
        BrdfTerm(diffuse_colour, "lambert", lambert_params),
        (specular_colour, "phong", phong_params),
    ]
    expected = diffuse_colour * brdf.lambert.eval(lambert_params, wo, wi) + specular_colour * brdf.phong.eval(
        phong_params, wo, wi
    )
    torch.testing.assert_close(eval_terms(terms, wo, wi), expected, **tolerances[DTYPE])
    # Lambert with a white albedo is 1/pi: the diffuse term alone is colour/pi above the horizon.
    torch.testing.assert_close(eval_terms(terms[:1], wo, wi), diffuse_colour / torch.pi, **tolerances[DTYPE])


def test_bad_terms_raise():
    wo = _directions(4, 4)
    params = brdf.LambertParams(torch.ones(4, 3, dtype=DTYPE))
    with pytest.raises(ValueError, match="unknown BRDF term 'lamber'; known terms: lambert, phong"):
        term_module("lamber")
    with pytest.raises(ValueError, match="at least one"):
        eval_terms([], wo, wo)
    with pytest.raises(ValueError, match=r"colour of BRDF term 'lambert' must have shape \(\.\.\., 3\)"):
        eval_terms([(torch.ones(4, dtype=DTYPE), "lambert", params)], wo, wo)
