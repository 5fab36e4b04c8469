"""The probe lights the F rows are refitted to (`relight_torch.transfer.responses`).

Two kinds, in this order of priority:

1. The shot's lights. Each is lit on the gathers as the relighter lights it (`gather_radiance`,
   the relighter's light samples per gather), carried through the bounces as F will see it
   ((I + M + ... + M^(B-1)) g_d with the baked M, `wavelet_light`) and split into its three colour
   channels (a colour-factored row is one scalar row for all three, and the gathers' albedo tints
   each channel differently). The gathers' own emission counts as one more light. First comes the
   shot as a whole (every light summed), then its lights, strongest first (by the mean of their
   light vector), all but the weakest, which is in their span: the shot, and any colour or
   intensity edit of its lights, is transferred exactly.
2. Objects lit uniformly. The gathers of an object under unit irradiance (radiance albedo / pi
   there, nothing elsewhere), carried through the bounces and summed over the channels (one
   scalar probe each): first the whole scene so lit, then one object at a time, those that reflect
   most of such light first (the most gather area times albedo). A light that moves off the shot's
   lights, or narrows, lands on the same objects, and these probes keep the largest objects' share
   of its transport (docs/TRANSFER.md has the measurements).

A row of k kept coefficients can honour few constraints without bending, so the probes are cut to
`probe_budget(k)`, a quarter of k in whole lights: the shot's lights take it first, the objects
what is left (on a shot with many lights, none), at most `MAX_OBJECT_PROBES`: the whole scene and
the objects that carry the most gather area times albedo; the others stay in the probe of the
whole scene. More object probes kept no more energy and bent the rows into ringing (a light added
in one place darkened pixels elsewhere; docs/TRANSFER.md). The order is also the priority: the
first `probe_budget(k')` probes of a bake that kept k >= k' coefficients are those a bake keeping
k' would make (cut there, the summed probes span what the dropped ones would have), which the
pilot's culled variants rely on.

Shadow links are left out of the probes (their occluder sets need the cache's per-object casters);
a probe only has to resemble the lights that will be relit.
"""

from __future__ import annotations

import dataclasses
import math

import torch

from pipeline.scene.types import Scene
from relight_torch.direct.settings import RelightSettings
from relight_torch.indirect import gather_sample_count
from relight_torch.indirect_samples import GatherSamples, gather_radiance
from relight_torch.transfer.relighter import GATHER_SAMPLES, wavelet_light
from relight_torch.transfer.sparse import SparseRows
from relight_torch.visibility.rays import RayCaster, RayVisibility

PROBES_PER_LIGHT = 3
"""Scalar probes per light: its red, green and blue channels."""
MAX_OBJECT_PROBES = 4
"""Probes of objects lit uniformly: the whole scene and the three objects that reflect most."""


def probe_budget(num_kept: int) -> int:
    """The number of scalar probes rows of `num_kept` coefficients are refitted to: a quarter of
    them, in whole lights, at least one light."""
    return PROBES_PER_LIGHT * max(1, num_kept // (4 * PROBES_PER_LIGHT))


def uniform_object_lights(gathers: GatherSamples, count: int) -> list[torch.Tensor]:
    """Up to `count` radiances (G, 3) of objects lit uniformly, in priority order (see the module doc).

    The first is every object under unit irradiance (albedo / pi on all gathers), then one object
    at a time, ranked by the light its gathers reflect (the sum of area times mean albedo), all but
    the weakest when they fit (it is the first's remainder). Objects that reflect nothing are left out.

    Args:
        gathers: the gathers; `object_id` None (a cache from before gathers carried it) gives
            only the whole scene.
        count: the most radiances returned.
    """
    if count < 1:
        return []
    reflected = gathers.albedo / math.pi
    if not bool((reflected > 0).any()):
        return []
    lights = [reflected]
    if gathers.object_id is None:
        return lights
    objects, of_gather = torch.unique(gathers.object_id, return_inverse=True)
    power = torch.zeros(objects.shape[0], dtype=gathers.area.dtype, device=gathers.area.device)
    power.index_add_(0, of_gather, gathers.area * gathers.albedo.mean(-1))
    ranked = torch.argsort(power, descending=True, stable=True)
    ranked = ranked[power[ranked] > 0][:-1]  # the weakest is the whole scene less the others
    for index in ranked[: count - 1].tolist():
        lights.append(reflected * (of_gather == index).unsqueeze(-1))
    return lights


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
        scene: the shot (its lights).
        gathers: the bake's gathers (CPU).
        caster: Embree over the shot (the gathers' shadow rays).
        bounce: the baked M (decoded), None for one bounce.
        num_bounces: B, as baked.
        num_kept: coefficients kept per F row.
        seed: seed of the gathers' light samples.

    Returns:
        float32 probes, Q <= `probe_budget(num_kept)`, in priority order: the lights'
        `PROBES_PER_LIGHT` rows each, then up to `MAX_OBJECT_PROBES` of objects, one each; empty
        (0, G) when the shot has neither lights, emission nor reflecting gathers.
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
    budget = probe_budget(num_kept)
    lights = ([torch.stack(vectors).sum(0)] + vectors[:-1]) if vectors else []
    rows = [vector.t() for vector in lights[: budget // PROBES_PER_LIGHT]]
    num_objects = min(MAX_OBJECT_PROBES, budget - PROBES_PER_LIGHT * len(rows))
    for radiance in uniform_object_lights(gathers, num_objects):
        rows.append(wavelet_light(radiance, bounce, num_bounces, gathers.side).sum(-1).unsqueeze(0))
    if not rows:
        return torch.zeros(0, gathers.num_gathers)
    return torch.cat(rows).float()
