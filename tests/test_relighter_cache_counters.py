"""The relighter re-renders only what an edit touches, and its cached images stay exact.

A tiny bake (the Cornell box at 32 x 32) is relit with the ceiling lamp plus a shaped sphere
light (a spot) and a rect light low in the box (which reaches under half the shading points, so
that its transport is kept sparse). `Relighter.counters` counts visibility and shading passes:

    colour, intensity, exposure, diffuse, specular  -> no pass (a rescale of cached images)
    ShapingAPI, Barzel controls                      -> one shading pass, of that light
    transform                                        -> one visibility and one shading pass

and after every edit the image equals a fresh Relighter's with the edited rig. The fast path is
also checked against its slow twin: a per-sample evaluation of the shaped light with
`shading.reflected_radiance`, as the deep-framebuffer relighter was first written.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from pipeline.bake.direct.bake import bake_direct
from pipeline.benchmarks.direct import checker_cookie, look_at
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES
from relight_torch.direct.images import colour_scale, unit_light
from relight_torch.direct.relighter import Relighter, open_relighter
from relight_torch.direct.settings import RelightSettings
from relight_torch.light_samples import fixed_light_samples
from relight_torch.lights.emission import sample_light
from relight_torch.lights.light import BarzelShaping, Light, LightKind, Shadow, Shaping
from relight_torch.lights.ratio import analytic_ratio
from relight_torch.lights.shadow import shadow_factor
from relight_torch.math.frame import to_local
from relight_torch.shading import reflected_radiance

SIZE = 32
SETTINGS = RelightSettings(
    area_samples=4, chunk_samples=1024, shadow_filter_radius=0
)  # the per-sample twin: unfiltered
UP = np.array([0.0, 1.0, 0.0])


@pytest.fixture(scope="module")
def baked(tmp_path_factory) -> Relighter:
    """A relighter of the shot's lights, whose G-buffer and Embree scene the tests share."""
    directory = tmp_path_factory.mktemp("cornell")
    bundled = SCENES["cornell_box"]
    scene = load_scene(bundled.write(directory / "scene"), width=SIZE, height=SIZE)
    layer = bake_direct(scene, find_camera(scene, bundled.camera), directory / "cache", "cornell_box")
    return open_relighter(layer, settings=SETTINGS)


def new_relighter(baked: Relighter, lights: list[Light]) -> Relighter:
    relighter = Relighter(baked.gbuffer, baked.visibility, baked.supersampling, baked.exposure_scale, SETTINGS)
    relighter.set_lights(lights)
    return relighter


def spot() -> Light:
    return Light(
        "/Test/Spot",
        LightKind.SPHERE,
        look_at(np.array([150.0, 420.0, 150.0]), np.array([300.0, 0.0, 300.0]), UP),
        intensity=2.0,
        radius=15.0,
        shaping=Shaping(focus=1.0, cone_angle=25.0, cone_softness=0.3),
    )


def low_rect() -> Light:
    return Light(
        "/Test/LowRect",
        LightKind.RECT,
        look_at(np.array([400.0, 120.0, 200.0]), np.array([400.0, 0.0, 200.0]), UP),
        intensity=3.0,
        width=60.0,
        height=40.0,
        color=(1.0, 0.9, 0.8),
    )


@pytest.fixture
def relighter(baked) -> Relighter:
    relighter = new_relighter(baked, baked.lights + [spot(), low_rect()])
    relighter.render()
    return relighter


def fresh_image(baked: Relighter, lights: list[Light]) -> torch.Tensor:
    return new_relighter(baked, lights).render()


def edited(light: Light, **changes) -> Light:
    return dataclasses.replace(light, **changes)


def moved(light: Light) -> Light:
    matrix = light.world_from_light.copy()
    matrix[:3, 3] += (30.0, -20.0, 10.0)
    return edited(light, world_from_light=matrix)


COLOUR_EDITS = {
    "color": lambda light: edited(light, color=(0.2, 0.5, 1.0)),
    "intensity": lambda light: edited(light, intensity=light.intensity * 3.0),
    "exposure": lambda light: edited(light, exposure=-1.5),
    "temperature": lambda light: edited(light, enable_color_temperature=True, color_temperature=3200.0),
    "diffuse": lambda light: edited(light, diffuse=0.25),
    "specular": lambda light: edited(light, specular=4.0),
}
SHADING_EDITS = {
    "cone": lambda light: edited(light, shaping=dataclasses.replace(light.shaping, cone_angle=15.0)),
    "focus": lambda light: edited(
        light, shaping=dataclasses.replace(light.shaping, focus=6.0, focus_tint=(0.2, 0.1, 0.0))
    ),
    "no_shaping": lambda light: edited(light, shaping=None),
    "cookie": lambda light: edited(light, barzel=BarzelShaping(cookie=checker_cookie(16, 4), cookie_scale=(0.6, 0.6))),
}
GEOMETRY_EDITS = {
    "move": moved,
    "radius": lambda light: edited(light, radius=light.radius * 2.0),
    "shadow_colour": lambda light: edited(light, shadow=Shadow(color=(0.3, 0.0, 0.0))),
}


def apply_edit(relighter: Relighter, path: str, edit) -> list[Light]:
    lights = [edit(light) if light.path == path else light for light in relighter.lights]
    relighter.set_light(next(light for light in lights if light.path == path))
    return lights


def assert_same_image(image: torch.Tensor, expected: torch.Tensor) -> None:
    torch.testing.assert_close(image, expected, rtol=1e-5, atol=1e-6 * float(expected.abs().max()))


@pytest.mark.parametrize("path", ["/Test/Spot", "/Test/LowRect"])
@pytest.mark.parametrize("name", sorted(COLOUR_EDITS))
def test_colour_edit_shades_nothing(baked, relighter, name, path):
    before = dict(relighter.counters)
    lights = apply_edit(relighter, path, COLOUR_EDITS[name])
    image = relighter.render()
    assert dict(relighter.counters) == before
    assert_same_image(image, fresh_image(baked, lights))


@pytest.mark.parametrize("name", sorted(SHADING_EDITS))
def test_shaping_edit_shades_that_light_only(baked, relighter, name):
    before = dict(relighter.counters)
    lights = apply_edit(relighter, "/Test/Spot", SHADING_EDITS[name])
    image = relighter.render()
    assert relighter.counters["visibility"] == before["visibility"]
    assert relighter.counters["shading"] == before["shading"] + 1
    assert_same_image(image, fresh_image(baked, lights))


@pytest.mark.parametrize("path", ["/Test/Spot", "/Test/LowRect"])
@pytest.mark.parametrize("name", sorted(GEOMETRY_EDITS))
def test_geometry_edit_retraces_that_light_only(baked, relighter, name, path):
    before = dict(relighter.counters)
    lights = apply_edit(relighter, path, GEOMETRY_EDITS[name])
    image = relighter.render()
    assert relighter.counters["visibility"] == before["visibility"] + 1
    assert relighter.counters["shading"] == before["shading"] + 1
    assert_same_image(image, fresh_image(baked, lights))


def test_sequence_of_edits_matches_a_fresh_relighter(baked, relighter):
    """Edits to several lights in turn (the cached sum of the others is rebuilt as the edited
    light changes); a removed light leaves no trace."""
    before = dict(relighter.counters)
    for path, edit in (
        ("/Test/Spot", COLOUR_EDITS["color"]),
        ("/Test/LowRect", moved),
        ("/Test/Spot", SHADING_EDITS["cone"]),
        ("/Test/LowRect", COLOUR_EDITS["exposure"]),
        ("/Test/Spot", COLOUR_EDITS["intensity"]),
    ):
        lights = apply_edit(relighter, path, edit)
        relighter.render()
    assert relighter.counters["visibility"] == before["visibility"] + 1
    assert relighter.counters["shading"] == before["shading"] + 2
    relighter.remove_light("/Test/LowRect")
    lights = [light for light in lights if light.path != "/Test/LowRect"]
    assert_same_image(relighter.render(), fresh_image(baked, lights))


def test_unchanged_rig_costs_nothing(relighter):
    before = dict(relighter.counters)
    relighter.set_lights(list(relighter.lights))
    relighter.render()
    assert dict(relighter.counters) == before


def slow_light_samples(relighter: Relighter, light: Light) -> torch.Tensor:
    """(N, 3) radiance the light reflects at every sub-sample, evaluated per sample of the SHAPED
    light with `reflected_radiance` (the slow twin of the relighter's cached transport); for a
    rect light the diffuse part times the ratio estimator's closed form over the samples' own
    unshaped, unshadowed estimate of it."""
    g = relighter.gbuffer
    u = fixed_light_samples(g.num_samples, relighter.num_light_samples(light), SETTINGS.seed)
    sample = sample_light(light, g.position, u)
    distance = relighter.visibility.occluder_distance(
        light, g.position, g.geometric_normal, sample.direction, sample.distance
    )
    facing = (sample.direction * g.geometric_normal[:, None]).sum(-1) > 0
    weight = sample.weight() * shadow_factor(light.shadow, torch.isfinite(distance), distance) * facing[..., None]
    wo_local = to_local(g.wo_world(), g.tangent, g.bitangent, g.normal)
    wi_local = to_local(sample.direction, g.tangent[:, None], g.bitangent[:, None], g.normal[:, None])
    params = g.params.with_sample_axis()
    diffuse = reflected_radiance(params, wo_local[:, None], wi_local, weight, light.diffuse, 0.0).mean(dim=1)
    specular = reflected_radiance(params, wo_local[:, None], wi_local, weight, 0.0, light.specular).mean(dim=1)
    estimate = (torch.isfinite(sample.distance) * facing * wi_local[..., 2].clamp_min(0.0) * sample.inverse_pdf()).mean(
        dim=1
    )
    ratio = analytic_ratio(light, g.position, g.normal, estimate)
    return (diffuse if ratio is None else diffuse * ratio[:, None]) + specular


def test_cached_transport_matches_per_sample_shading(relighter):
    """Shaped, cookied, shadow-coloured, lobe-weighted lights: the unshaped transport times the
    shaping factor equals shading the shaped light's samples directly."""
    rig = [
        edited(
            spot(),
            diffuse=0.5,
            specular=2.0,
            shadow=Shadow(color=(0.2, 0.3, 0.0)),
            barzel=BarzelShaping(cookie=checker_cookie(16, 4), cookie_scale=(0.6, 0.6)),
        ),
        edited(low_rect(), exposure=1.0, shaping=Shaping(cone_angle=50.0, cone_softness=0.5)),
    ]
    relighter.set_lights(rig)
    g = relighter.gbuffer
    expected = g.params.emissive_color.clone()
    for light in rig:
        unit = unit_light(light)
        expected += torch.as_tensor(colour_scale(light), dtype=expected.dtype) * slow_light_samples(relighter, unit)
    assert float(expected.abs().max()) > 0
    torch.testing.assert_close(relighter.render_samples(), expected, rtol=1e-4, atol=1e-5 * float(expected.max()))
