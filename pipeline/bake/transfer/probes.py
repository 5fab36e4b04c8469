"""The probe lights the F rows are refitted to (`relight_torch.transfer.responses`): the shot's lights.

Each light of the shot is lit on the gathers as the relighter lights it (`gather_radiance`, the
relighter's light samples per gather), carried through the bounces as F will see it
((I + M + ... + M^(B-1)) g_d with the baked M, `wavelet_light`) and split into its three colour
channels (a colour-factored row is one scalar row for all three, and the gathers' albedo tints
each channel differently). The gathers' own emission is one more probe light. A row of k kept
coefficients can honour few constraints without bending, so at most `num_kept // PROBES_PER_LIGHT
// 4` probe lights are kept, and the weakest lights beyond them (by the mean of their light
vector) are summed into the last one: the shot as a whole is always among the probes.

Shadow links are left out of the probes (their occluder sets need the cache's per-object casters);
a probe only has to resemble the lights that will be relit.
"""

from __future__ import annotations

import dataclasses

import torch

from pipeline.scene.types import Scene
from relight_torch.direct.settings import RelightSettings
from relight_torch.indirect import gather_sample_count
from relight_torch.indirect_samples import GatherSamples, gather_radiance
from relight_torch.transfer.relighter import GATHER_SAMPLES, wavelet_light
from relight_torch.transfer.sparse import SparseRows
from relight_torch.visibility.rays import RayCaster, RayVisibility

PROBES_PER_LIGHT = 3
"""Scalar probes per probe light: its red, green and blue channels."""


def probe_lights(
    scene: Scene,
    gathers: GatherSamples,
    caster: RayCaster,
    bounce: SparseRows | None,
    num_bounces: int,
    num_kept: int,
    seed: int,
) -> torch.Tensor:
    """(Q, G) the Haar coefficients of the scalar probe lights of the shot's F rows (see the module doc).

    Args:
        scene: the shot (its lights and objects).
        gathers: the bake's gathers (CPU).
        caster: Embree over the shot (the gathers' shadow rays).
        bounce: the baked M (decoded), None for one bounce.
        num_bounces: B, as baked.
        num_kept: coefficients kept per F row.
        seed: seed of the gathers' light samples.

    Returns:
        float32 probes, `PROBES_PER_LIGHT` per probe light; empty (0, G) when the shot has neither
        lights nor emissive gathers.
    """
    visibility = RayVisibility(caster)
    object_paths = [obj.path for obj in scene.objects]
    dome_samples = RelightSettings().dome_samples
    vectors = []
    for light in scene.lights:
        light = dataclasses.replace(light, shadow_link=None)
        samples = gather_sample_count(light, GATHER_SAMPLES, dome_samples)
        radiance = gather_radiance(light, gathers, visibility, samples, seed, object_paths=object_paths)
        vectors.append(wavelet_light(radiance, bounce, num_bounces, gathers.side))
    if bool((gathers.emission != 0).any()):
        vectors.append(wavelet_light(gathers.emission, bounce, num_bounces, gathers.side))
    # Strongest first (the Haar box coefficient is the light's sum over the gathers, up to a constant).
    vectors.sort(key=lambda vector: -float(vector[0].abs().sum()))
    num_lights = max(1, num_kept // PROBES_PER_LIGHT // 4)
    if len(vectors) > num_lights:
        vectors = vectors[: num_lights - 1] + [torch.stack(vectors[num_lights - 1 :]).sum(0)]
    if not vectors:
        return torch.zeros(0, gathers.num_gathers)
    return torch.cat([vector.t() for vector in vectors]).float()
