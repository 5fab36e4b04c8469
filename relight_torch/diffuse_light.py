"""Direct light reflected once by diffuse points: the light the indirect methods' gathers re-emit.

Shared by the transfer method (its gather cloud, g_d) and the clustered-gather method (D(g) of
the clustered-gather paper's equations 2 and 3), through the same light kernels and visibility as the view samples,
and the same UsdLux linking: a light's light link masks the points of the objects it does not
light (as `Relighter.light_mask` does for view samples), and its shadow link picks the occluders its
shadow rays see (`visibility.occluder_distance` honours `Light.shadow_link`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from relight_torch.errors import RelightError
from relight_torch.light_samples import fixed_light_samples
from relight_torch.lights.emission import sample_light
from relight_torch.lights.light import Light
from relight_torch.lights.linking import linked_points
from relight_torch.lights.ratio import analytic_ratio, estimate_weights
from relight_torch.lights.shadow import shadow_factor
from relight_torch.visibility import Visibility


def diffuse_radiance(
    light: Light,
    position: torch.Tensor,
    normal: torch.Tensor,
    albedo: torch.Tensor,
    visibility: Visibility,
    num_samples: int,
    seed: int = 0,
    chunk_points: int = 1 << 16,
    object_id: torch.Tensor | None = None,
    object_paths: Sequence[str] | None = None,
) -> torch.Tensor:
    """Radiance (G, 3) leaving G diffuse points after one reflection of `light`.

    L = diffuse * albedo / pi * E, E the irradiance from `num_samples` fixed light samples per
    point through the view samples' kernels and visibility (`sample_light`, `occluder_distance`,
    `shadow_factor`), on the side `normal` points to; for lights with a closed-form unshadowed
    irradiance, times the ratio estimator's factor (`lights.ratio.analytic_ratio`), as the
    relighter does.

    Args:
        light: the light (a unit light to cache per light).
        position: (G, 3) world points; normal: (G, 3) unit receiving normals; albedo: (G, 3).
        visibility: shadow queries.
        num_samples: light samples per point (1 for delta lights).
        seed: seed of the fixed sample pattern.
        chunk_points: points processed together.
        object_id: (G,) int index of each point's object into `object_paths`; needed only by a
            light with a light link (points of objects outside it get no light).
        object_paths: the scene's object prim paths, by object id.

    Raises:
        RelightError: the light has a light link and the points' objects are unknown.
    """
    num_points = position.shape[0]
    u = fixed_light_samples(num_points, num_samples, seed, position.device, position.dtype)
    linked = link_mask(light, object_id, object_paths)
    if linked is not None:  # unlinked points get no light and cast no shadow rays
        lit = torch.nonzero(linked).squeeze(-1)
        position, normal, u = position[lit], normal[lit], u[lit]
    irradiance = torch.zeros_like(position)
    for start in range(0, position.shape[0], chunk_points):
        chunk = slice(start, start + chunk_points)
        sample = sample_light(light, position[chunk], u[chunk])
        cosine = (sample.direction * normal[chunk].unsqueeze(1)).sum(-1).clamp(min=0.0)
        weight = sample.weight() * cosine.unsqueeze(-1)
        # Shadow rays only for the (point, sample) pairs that can carry light: samples the light
        # cannot emit (pdf 0) and points facing away cost nothing. Shaping is left out of this test
        # so that a shaping edit asks the same shadow queries (remembered by the gather relighter).
        point, live = torch.nonzero((sample.pdf > 0) & (cosine > 0), as_tuple=True)
        distance = torch.full_like(sample.distance, math.inf)
        if point.numel():
            distance[point, live] = visibility.occluder_distance(
                light,
                position[chunk][point],
                normal[chunk][point],
                sample.direction[point, live].unsqueeze(1),
                sample.distance[point, live].unsqueeze(1),
            ).squeeze(1)
        shadow = shadow_factor(light.shadow, torch.isfinite(distance), distance)
        irradiance[chunk] = (weight * shadow).mean(dim=1)
        # The ratio estimator (lights.ratio): the samples' unshadowed estimate against the closed form.
        estimate = (estimate_weights(light, sample.distance, sample.radiance) * cosine * sample.inverse_pdf()).mean(1)
        ratio = analytic_ratio(light, position[chunk], normal[chunk], estimate)
        if ratio is not None:
            irradiance[chunk] *= ratio.unsqueeze(-1)
    if linked is not None:
        irradiance = irradiance.new_zeros(num_points, 3).index_copy_(0, lit, irradiance)
    return light.diffuse * albedo / math.pi * irradiance


def link_mask(light: Light, object_id: torch.Tensor | None, object_paths: Sequence[str] | None) -> torch.Tensor | None:
    """(G,) bool on `object_id`'s device: whether the light's light link includes each point's
    object; None when the light links every object."""
    if light.light_link is None:
        return None
    if object_id is None or object_paths is None:
        raise RelightError(
            f"{light.path}: light linking of indirect light needs the gathers' object ids "
            f"(re-bake the cache with this version)"
        )
    return linked_points(object_paths, light.light_link, object_id)
