"""The gathers' re-emitted albedo: what the whole UsdPreviewSurface BRDF reflects under uniform light."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pipeline.bake.gather_cloud import create_gathers, reemitted_albedo
from pipeline.scene import load_scene
from pipeline.scenes import SCENES
from relight_torch.brdf import preview_surface
from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.math.sampling import hemisphere_quadrature


def _params(rows: list[dict[str, object]], dtype: torch.dtype = torch.float32) -> PreviewSurfaceParams:
    """Parameters of a few materials (UsdPreviewSurface fallbacks for what a row leaves out)."""
    defaults = {
        "diffuse_color": (0.18, 0.18, 0.18),
        "emissive_color": (0.0, 0.0, 0.0),
        "specular_color": (0.0, 0.0, 0.0),
        "metallic": 0.0,
        "roughness": 0.5,
        "clearcoat": 0.0,
        "clearcoat_roughness": 0.01,
        "ior": 1.5,
        "opacity": 1.0,
        "use_specular_workflow": False,
    }
    values = {
        name: np.array(
            [row.get(name, default) for row in rows], dtype=bool if name == "use_specular_workflow" else None
        )
        for name, default in defaults.items()
    }
    params = PreviewSurfaceParams.from_numpy(
        {k: v if v.dtype == bool else v.astype(np.float32) for k, v in values.items()}
    )
    return params.to(dtype=dtype) if dtype != torch.float32 else params


MATERIALS = [
    {"diffuse_color": (1.0, 0.71, 0.29), "metallic": 1.0, "roughness": 0.6},  # rough gold
    {"diffuse_color": (1.0, 1.0, 1.0), "metallic": 1.0, "roughness": 0.7},  # white metal
    {"diffuse_color": (0.6, 0.05, 0.04), "roughness": 0.6},  # red plastic
    {"diffuse_color": (0.74, 0.74, 0.74), "roughness": 1.0},  # matte white
    {"diffuse_color": (0.05, 0.15, 0.5), "roughness": 0.6, "clearcoat": 1.0, "clearcoat_roughness": 0.6},
]
"""Lobes wide enough for the slow twin's midpoint grid (it converges slowly on sharp ones)."""


def _quadrature_albedo(params: PreviewSurfaceParams, side: int, block: int = 64) -> torch.Tensor:
    """(N, 3) 1/pi * sum over a (theta, phi) midpoint grid of wo and of wi of f cos cos: the slow twin."""
    directions, weights = hemisphere_quadrature(side, 2 * side, dtype=torch.float64)
    num, count = params.roughness.shape[0], directions.shape[0]
    total = torch.zeros(num, 3, dtype=torch.float64)
    expanded = params.with_sample_axis()
    for start in range(0, count, block):  # `block` values of wo against every wi
        wo = directions[start : start + block]
        pairs = wo.shape[0] * count
        wo_all = wo[:, None, :].expand(-1, count, 3).reshape(1, pairs, 3).expand(num, -1, -1)
        wi_all = directions.expand(wo.shape[0], count, 3).reshape(1, pairs, 3).expand(num, -1, -1)
        f = preview_surface.eval(expanded, wo_all, wi_all)
        cosines = (weights[start : start + block, None] * wo[:, 2:] * (weights * directions[:, 2])[None, :]).reshape(-1)
        total += (f * cosines[None, :, None]).sum(1)
    return total / math.pi


@pytest.mark.slow
def test_reemitted_albedo_matches_a_quadrature():
    params = _params(MATERIALS, torch.float64)
    expected = _quadrature_albedo(params, 24)
    estimated = reemitted_albedo(params)
    torch.testing.assert_close(estimated, expected, rtol=0.02, atol=2e-3)


def test_reemitted_albedo_conserves_energy_and_keeps_a_matte_surface_matte():
    params = _params(MATERIALS)
    albedo = reemitted_albedo(params)
    assert bool((albedo <= 1.0 + 1e-3).all()) and bool((albedo >= 0.0).all())
    # A metal reflects (all of it specular); a matte dielectric's albedo stays its diffuse colour
    # within the few per cent its Fresnel moves between the diffuse and the specular lobe.
    assert float(albedo[1].min()) > 0.5
    torch.testing.assert_close(albedo[3], torch.full((3,), 0.74), rtol=0.03, atol=0.0)


@pytest.mark.slow
def test_metal_gathers_reemit_light(tmp_path):
    # Gathers used to re-emit the diffuse colour alone: a metal's gathers were black, and the light
    # metals reflect towards other surfaces (31 % of the glossy scene's indirect light under a dome)
    # was missing from the indirect part.
    bundled = SCENES["glossy"]
    scene = load_scene(bundled.write(tmp_path), width=32, height=24)
    gathers = create_gathers(scene, 1024)
    paths = [obj.path for obj in scene.objects]
    gold = gathers.object_id == next(i for i, p in enumerate(paths) if p.endswith("GoldSphere"))
    backdrop = gathers.object_id == next(i for i, p in enumerate(paths) if p.endswith("Backdrop"))
    assert bool(gold.any()) and bool(backdrop.any())
    assert float(gathers.albedo[gold, 0].min()) > 0.9  # gold's F0 is (1.00, 0.71, 0.29)
    torch.testing.assert_close(gathers.albedo[backdrop].mean(0), torch.full((3,), 0.35), rtol=0.03, atol=0.0)
