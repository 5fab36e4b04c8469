"""Light reflected by surface points: the one product every renderer in the project evaluates.

    L_o = f_r(wo, wi) cos(theta_i) L_i

with the UsdLux per-lobe multipliers `inputs:diffuse` and `inputs:specular` applied to the
diffuse and specular parts of UsdPreviewSurface. The reference path tracer, the deep-framebuffer
relighter and the indirect bakers all call `reflected_radiance`.
"""

from __future__ import annotations

import torch

from relight_torch.brdf import preview_surface
from relight_torch.brdf.preview_surface import PreviewSurfaceParams


def reflected_radiance(
    params: PreviewSurfaceParams,
    wo_local: torch.Tensor,
    wi_local: torch.Tensor,
    radiance: torch.Tensor,
    diffuse_scale: float = 1.0,
    specular_scale: float = 1.0,
) -> torch.Tensor:
    """Radiance reflected towards wo from light arriving along wi.

    Args:
        params: N shading points' UsdPreviewSurface parameters.
        wo_local, wi_local: (N, 3) unit directions in the shading frame (z = normal), both
            pointing away from the surface.
        radiance: (N, 3) incident radiance L_i along wi (W sr^-1 m^-2, RGB).
        diffuse_scale, specular_scale: the light's `inputs:diffuse` / `inputs:specular`.

    Returns:
        (N, 3) reflected radiance; zero where wi or wo is below the horizon.
    """
    if diffuse_scale == 1.0 and specular_scale == 1.0:
        f = preview_surface.eval(params, wo_local, wi_local)
    else:
        diffuse, specular = preview_surface.split(params, wo_local, wi_local)
        f = diffuse * diffuse_scale + specular * specular_scale
    cos_theta = wi_local[..., 2].clamp(min=0.0)
    return f * cos_theta[..., None] * radiance
