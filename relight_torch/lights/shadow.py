"""UsdLux ShadowAPI applied to a visibility test (USD_EXR_NOTES 1.4; non-physical controls).

Whoever computes visibility (tracer, baker, relighter) multiplies the light's contribution by
`shadow_factor`: a shadowed point receives the light times `shadow.color` instead of nothing,
occluders farther than `distance` from the shaded point cast no shadow, and within the last
`falloff` of that distance the shadow fades out (with `falloff_gamma`).
"""

from __future__ import annotations

import torch

from relight_torch.lights.light import Shadow


def shadow_factor(shadow: Shadow, occluded: torch.Tensor, occluder_distance: torch.Tensor) -> torch.Tensor:
    """RGB visibility factor of one light.

    strength = 1 for an occluded point, times (for distance >= 0) the fade
    clamp((distance - x) / falloff, 0, 1)^falloff_gamma (falloff > 0) or [x <= distance]
    (falloff <= 0), with x the occluder's distance; factor = 1 - strength (1 - color).
    Disabled shadows (enable false) give 1 everywhere.

    Args:
        shadow: the light's ShadowAPI values.
        occluded: (...) bool, whether the shadow ray hit something before the light.
        occluder_distance: (...) world distance from the shaded point to the first occluder
            (ignored where not occluded; the dtype and device of the result).

    Returns:
        (..., 3) factor multiplying the light's radiance.
    """
    like = occluder_distance
    if not shadow.enable:
        return torch.ones(*like.shape, 3, device=like.device, dtype=like.dtype)
    color = torch.as_tensor(shadow.color, device=like.device, dtype=like.dtype)
    return 1.0 - shadow_strength(shadow, occluded, occluder_distance).unsqueeze(-1) * (1.0 - color)


def shadow_strength(shadow: Shadow, occluded: torch.Tensor, occluder_distance: torch.Tensor) -> torch.Tensor:
    """(...) the strength of `shadow_factor` (1 for an occluded point, faded by distance); 0
    everywhere when shadows are disabled. With a grey shadow colour c the factor is the scalar
    1 - strength (1 - c)."""
    like = occluder_distance
    if not shadow.enable:
        return torch.zeros_like(like)
    strength = occluded.to(like.dtype)
    if shadow.distance >= 0:
        if shadow.falloff > 0:
            fade = ((shadow.distance - occluder_distance) / shadow.falloff).clamp(0.0, 1.0) ** shadow.falloff_gamma
        else:
            fade = (occluder_distance <= shadow.distance).to(like.dtype)
        strength = strength * fade
    return strength
