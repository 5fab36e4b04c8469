"""Helpers shared by the direct relighter's tests: uniform materials and a relighter's twin."""

from __future__ import annotations

import torch

from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.direct.relighter import Relighter
from relight_torch.gbuffer import GBuffer


def matte_params(n: int) -> PreviewSurfaceParams:
    """n points of one grey (0.5), half-rough (0.5) dielectric material."""

    def full(value: float, channels: int = 0) -> torch.Tensor:
        return torch.full((n, channels) if channels else (n,), value)

    return PreviewSurfaceParams(
        diffuse_color=full(0.5, 3),
        emissive_color=full(0.0, 3),
        specular_color=full(0.0, 3),
        metallic=full(0.0),
        roughness=full(0.5),
        clearcoat=full(0.0),
        clearcoat_roughness=full(0.01),
        ior=full(1.5),
        opacity=full(1.0),
        use_specular_workflow=torch.zeros(n, dtype=torch.bool),
    )


def twin(relighter: Relighter, gbuffer: GBuffer) -> Relighter:
    """A fresh relighter of `gbuffer` with `relighter`'s shadows, settings, paths and lights: nothing
    it kept is shared."""
    fresh = Relighter(
        gbuffer,
        relighter.visibility,
        relighter.supersampling,
        relighter.exposure_scale,
        relighter.settings,
        relighter.object_paths,
        relighter.material_paths,
    )
    fresh.set_lights(relighter.lights)
    return fresh
