"""A dome light's samples joined by samples of the BRDF's glossy lobes, with multiple importance
sampling (Veach & Guibas 1995, the balance heuristic).

A dome sampled by its luminance alone finds a narrow glossy lobe with a handful of its samples:
the glossy reflection of a bright sky is the noisiest term of a dome-lit frame. Half of the
point's fixed samples (the odd ones, so that each half keeps the pattern's strata in its first
number) are drawn from the specular and clearcoat lobes instead (`preview_surface.sample` with
`diffuse=False`). The specular sum then weighs every sample by cos / (S_L p_L + S_B p_B), p_L the
dome's density and p_B the lobes', while the diffuse sum keeps the dome's own samples,
cos / (S_L p_L), which its ratio estimator corrects (`lights.ratio`).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from relight_torch.brdf import preview_surface
from relight_torch.direct.points import take
from relight_torch.gbuffer import GBuffer
from relight_torch.lights.emission import LightSample, sample_light, trace_light
from relight_torch.lights.light import Light, LightKind
from relight_torch.math.frame import to_local, to_world


class WeightedSamples(NamedTuple):
    """A light's samples at C points, S each, samples leading.

    Attributes:
        direction: (S, C, 3) unit world directions towards the light.
        distance: (S, C) world distance to the emitting point (inf for distant and dome lights).
        radiance: (S, C, 3) radiance arriving along `direction`.
        diffuse_weight: (S, C) the diffuse sum's weight per sample, without the cosine:
            1 / (pdf S) for the light's samples, 0 for the BRDF's.
        specular_weight: (S, C) the glossy lobes' weight per sample, without the cosine (the same
            tensor as `diffuse_weight` without BRDF samples).
    """

    direction: torch.Tensor
    distance: torch.Tensor
    radiance: torch.Tensor
    diffuse_weight: torch.Tensor
    specular_weight: torch.Tensor


def samples_brdf(light: Light) -> bool:
    """Whether the light's samples are joined by BRDF samples: domes, which cover the hemisphere."""
    return light.kind is LightKind.DOME


def weighted_samples(
    light: Light, gbuffer: GBuffer, chunk: slice | torch.Tensor, u: torch.Tensor, wo: torch.Tensor
) -> WeightedSamples:
    """The light's samples at the points `chunk` of `gbuffer` (C of them) from their fixed numbers
    u (C, S, 2), joined by BRDF samples where `samples_brdf` (module doc); wo: (C, 3) unit
    directions from the points towards the camera."""
    position = take(gbuffer.position, chunk)
    if not samples_brdf(light) or u.shape[1] < 2:
        sample = _samples_first(sample_light(light, position, u))
        weight = sample.inverse_pdf() / u.shape[1]
        return WeightedSamples(sample.direction, sample.distance, sample.radiance, weight, weight)
    light_u, brdf_u = u[:, 0::2], u[:, 1::2]
    num_light, num_brdf = light_u.shape[1], brdf_u.shape[1]
    sample = _samples_first(sample_light(light, position, light_u))
    params = gbuffer.params.index(chunk)
    frame = (take(gbuffer.tangent, chunk), take(gbuffer.bitangent, chunk), take(gbuffer.normal, chunk))
    wo_local = to_local(wo, *frame)
    brdf_local, brdf_pdf = preview_surface.sample(params, wo_local, brdf_u.transpose(0, 1), diffuse=False)
    brdf_direction = torch.nn.functional.normalize(to_world(brdf_local, *frame), dim=-1)
    brdf_distance, brdf_radiance, brdf_light_pdf = trace_light(light, position, brdf_direction)
    light_brdf_pdf = preview_surface.pdf(params, wo_local, to_local(sample.direction, *frame), diffuse=False)
    denominator = num_light * torch.cat((sample.pdf, brdf_light_pdf)) + num_brdf * torch.cat((light_brdf_pdf, brdf_pdf))
    # A lost BRDF sample (pdf 0) carries nothing: its direction was not drawn from p_B.
    drawn = torch.cat((sample.pdf > 0, brdf_pdf > 0))
    specular_weight = torch.where(drawn, 1.0 / torch.where(drawn, denominator, 1.0), 0.0)
    diffuse_weight = torch.cat((sample.inverse_pdf() / num_light, torch.zeros_like(brdf_pdf)))
    return WeightedSamples(
        torch.cat((sample.direction, brdf_direction)),
        torch.cat((sample.distance, brdf_distance)),
        torch.cat((sample.radiance, brdf_radiance)),
        diffuse_weight,
        specular_weight,
    )


def _samples_first(sample: LightSample) -> LightSample:
    """The sample with its (S, C, ...) views (`sample_light` returns (C, S, ...) views of them)."""
    return LightSample(
        sample.direction.transpose(0, 1),
        sample.distance.transpose(0, 1),
        sample.radiance.transpose(0, 1),
        sample.pdf.transpose(0, 1),
        sample.is_delta,
    )
