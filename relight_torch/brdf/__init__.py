"""BRDFs as batched torch functions, one module per model.

Every module exposes, over directions in the local shading frame (z = shading normal, both
directions pointing away from the surface, wo towards the viewer, wi towards the light):

    eval(params, wo_local (..., 3), wi_local (..., 3)) -> (..., 3)  f_r in 1/sr, cosine NOT included
    sample(params, wo_local (..., 3), u (..., 2)) -> (wi_local (..., 3), pdf (...))
    pdf(params, wo_local, wi_local) -> (...)  solid-angle density of `sample`

eval is 0 when wo or wi is below the horizon. `sample` returns pdf == pdf(wi); a pdf of 0 marks
a lost sample (below the horizon), whose weight f cos / pdf must be taken as 0. Params are
frozen dataclasses of tensors (`relight_torch.brdf.params.BrdfParams`).

All models are reciprocal. Energy: Lambert, Oren-Nayar, Phong, Blinn-Phong, Cook-Torrance, Ward
and Minnaert with k >= 1 keep the directional albedo <= 1 for reflectances <= 1; Minnaert with
k < 1 and Storm's UsdPreviewSurface (at low roughness, and near grazing angles) do not (see each
module).
"""

from relight_torch.brdf import (
    blinn_phong,
    cook_torrance,
    lambert,
    minnaert,
    oren_nayar,
    phong,
    preview_surface,
    ward,
)
from relight_torch.brdf.blinn_phong import BlinnPhongParams
from relight_torch.brdf.cook_torrance import CookTorranceParams
from relight_torch.brdf.lambert import LambertParams
from relight_torch.brdf.minnaert import MinnaertParams
from relight_torch.brdf.oren_nayar import OrenNayarParams
from relight_torch.brdf.params import BrdfParams
from relight_torch.brdf.phong import PhongParams
from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.brdf.terms import TERM_MODULES, BrdfTerm, eval_terms, term_module
from relight_torch.brdf.ward import WardParams

__all__ = [
    "TERM_MODULES",
    "BlinnPhongParams",
    "BrdfParams",
    "BrdfTerm",
    "CookTorranceParams",
    "LambertParams",
    "MinnaertParams",
    "OrenNayarParams",
    "PhongParams",
    "PreviewSurfaceParams",
    "WardParams",
    "blinn_phong",
    "cook_torrance",
    "eval_terms",
    "lambert",
    "minnaert",
    "oren_nayar",
    "phong",
    "preview_surface",
    "term_module",
    "ward",
]
