"""The ratio estimator (lights/ratio.py) and its filtered visibility (visibility/surface_filter.py)
in the relighter, on the Cornell box at 96 x 96 with one sub-sample per pixel.

The truth is plain Monte Carlo with 256 light samples (the same shadow rays, no closed form): a few
samples with the closed-form factor land much closer to it than plain Monte Carlo does, with and
without ShapingAPI controls (applied per sample after the factor); both estimators converge to the
same image; filtering the visibility of one sample per point removes most of the rest of the noise.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from pipeline.bake.direct.bake import bake_direct
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES
from relight_torch.direct.relighter import Relighter, open_relighter
from relight_torch.direct.settings import RelightSettings, auto_filter_radius
from relight_torch.lights import ratio as ratio_estimator
from relight_torch.lights.light import LightKind, Shaping
from relight_torch.metrics import psnr
from relight_torch.visibility.surface_filter import SurfaceFilter

SIZE = 96


@pytest.fixture(scope="module")
def baked(tmp_path_factory) -> Relighter:
    directory = tmp_path_factory.mktemp("cornell")
    bundled = SCENES["cornell_box"]
    scene = load_scene(bundled.write(directory / "scene"), width=SIZE, height=SIZE)
    layer = bake_direct(scene, find_camera(scene, bundled.camera), directory / "cache", "cornell_box", 1, 1)
    return open_relighter(layer)


def render(baked: Relighter, lights, samples: int, radius: int = 0):
    relighter = Relighter(
        baked.gbuffer,
        baked.visibility,
        baked.supersampling,
        baked.exposure_scale,
        RelightSettings(area_samples=samples, shadow_filter_radius=radius),
    )
    relighter.set_lights(lights)
    return relighter.render().numpy()


def plain(baked: Relighter, lights, samples: int, monkeypatch):
    with monkeypatch.context() as patch:
        patch.setattr(ratio_estimator, "has_closed_form", lambda light: False)
        return render(baked, lights, samples)


# shaping -> (least PSNR of 4 samples with the ratio against the truth, least gain over plain
# Monte Carlo with the same 4 samples); measured 43.6 / 7.3, 45.4 / 3.9, 43.4 / 3.4 dB.
@pytest.mark.parametrize(
    ("shaping", "min_db", "min_gain_db"),
    [
        (None, 43.1, 6.5),
        (Shaping(focus=4.0), 44.9, 3.4),
        (Shaping(cone_angle=40.0, cone_softness=0.4), 42.9, 3.0),
    ],
)
def test_few_samples_with_the_ratio_beat_plain_monte_carlo(baked, monkeypatch, shaping, min_db, min_gain_db):
    lights = [dataclasses.replace(light, shaping=shaping) for light in baked.lights]
    truth = plain(baked, lights, 256, monkeypatch)
    ratio = psnr(render(baked, lights, 4), truth)
    assert ratio >= min_db and ratio >= psnr(plain(baked, lights, 4, monkeypatch), truth) + min_gain_db
    assert psnr(render(baked, lights, 256), truth) >= 55.0  # measured 55.6-62.7 dB: the same limit


def test_filtered_visibility_of_one_sample(baked, monkeypatch):
    # Measured: plain 29.8, ratio 35.0, filtered r = 1 43.2, r = 2 41.4 dB (the wider box blurs
    # the penumbrae of a 96-pixel image: the radius is for images whose penumbrae span many pixels).
    truth = plain(baked, baked.lights, 256, monkeypatch)
    ratio = psnr(render(baked, baked.lights, 1), truth)
    assert psnr(plain(baked, baked.lights, 1, monkeypatch), truth) <= ratio - 4.5
    assert psnr(render(baked, baked.lights, 1, radius=1), truth) >= max(ratio + 7.5, 42.7)


def test_the_filter_stays_on_one_surface(baked):
    g = baked.gbuffer
    radius = 3
    floor = (g.normal[:, 1] > 0.99).to(g.position.dtype)
    counts = SurfaceFilter(g, radius)(torch.stack((floor, torch.ones_like(floor)), dim=-1))
    walls = g.normal[:, 1].abs() < 0.01
    assert bool(walls.any()) and float(counts[walls, 0].abs().max()) == 0.0  # nothing leaks off the floor
    assert float(counts[:, 1].max()) == (2 * radius + 1) ** 2 and float(counts[:, 1].min()) >= 1.0
    # Where every neighbour is fully lit, the filtered visibility is exactly 1.
    assert torch.equal(counts[:, 1] / counts[:, 1], torch.ones_like(floor))


def test_visibility_is_filtered_only_near_shadows_with_the_numbers_of_the_whole_filter(baked, monkeypatch):
    from relight_torch.visibility import surface_filter

    monkeypatch.setattr(surface_filter, "TILE", 16)  # 36 tiles over the 96 x 96 image
    monkeypatch.setattr(surface_filter, "MAX_TILE_FRACTION", 1.0)  # tiles however many
    g = baked.gbuffer
    generator = torch.Generator().manual_seed(4)
    weights = torch.rand(g.num_samples, generator=generator, dtype=g.position.dtype) + 0.1
    weights[g.normal[:, 0] > 0.99] = 0.0  # a wall the light does not reach
    # A shadow with a noisy penumbra on the floor, wholly lit elsewhere.
    offset = (g.position[:, 0] - g.position[:, 0].mean()).abs()
    lit = torch.where(offset < 0.1 * offset.max(), 0.0, 1.0)
    penumbra = (offset >= 0.1 * offset.max()) & (offset < 0.15 * offset.max())
    lit = torch.where(penumbra, (torch.rand(lit.shape, generator=generator) < 0.5).to(lit.dtype), lit)
    sums = torch.stack((weights * lit, weights), dim=-1)
    f = SurfaceFilter(g, 2)
    filtered = f(sums)
    whole = torch.where(filtered[:, 1] > 0, filtered[:, 0] / torch.where(filtered[:, 1] > 0, filtered[:, 1], 1.0), 0.0)
    calls = []
    original = f._filter_tiles
    monkeypatch.setattr(f, "_filter_tiles", lambda *args: calls.append(args[1].numel()) or original(*args))
    tiles = f.visibility(sums)
    own = weights > 0
    assert torch.equal(tiles[own], whole[own])
    assert bool(((tiles[~own] == whole[~own]) | (tiles[~own] == 1.0)).all())
    assert 0 < calls[0] < 36  # only the tiles near the shadow's edges were filtered
    # No shadow at all: nothing to filter, every reached point exactly 1.
    calls.clear()
    assert torch.equal(f.visibility(torch.stack((weights, weights), dim=-1))[own], torch.ones_like(weights[own]))
    assert not calls
    # Shadows over more tiles than MAX_TILE_FRACTION: the whole image in one pass, the same numbers.
    monkeypatch.setattr(surface_filter, "MAX_TILE_FRACTION", 0.0)
    assert torch.equal(f.visibility(sums), whole) and not calls


def test_the_automatic_filter_radius_follows_the_image_size():
    assert [
        auto_filter_radius(size, 1)
        for size in ((48, 64), (160, 160), (239, 1000), (240, 320), (400, 400), (480, 640), (1080, 1920))
    ] == [0, 0, 0, 2, 3, 4, 4]
    assert auto_filter_radius((960, 1280), 2) == 8  # sub-samples: the same 4 pixels


def test_a_filtered_light_takes_one_sample_at_matte_points_and_all_at_glossy_ones(baked):
    def samples(gbuffer, **settings):
        relighter = Relighter(
            gbuffer, baked.visibility, baked.supersampling, baked.exposure_scale, RelightSettings(**settings)
        )
        relighter.set_lights(baked.lights)
        return relighter.render_samples()

    # The Cornell box is matte: a filtered rect light takes `filtered_area_samples` everywhere.
    assert torch.equal(
        samples(baked.gbuffer, shadow_filter_radius=1), samples(baked.gbuffer, shadow_filter_radius=1, area_samples=1)
    )
    # Make the floor and the boxes' tops glossy: they keep 16 samples, the rest takes 1. The filter
    # never mixes the two (other surfaces), so each part equals a render with one count everywhere.
    up = baked.gbuffer.normal[:, 1] > 0.99
    roughness = torch.where(up, 0.3, baked.gbuffer.params.roughness)
    shiny = dataclasses.replace(baked.gbuffer, params=dataclasses.replace(baked.gbuffer.params, roughness=roughness))
    mixed = samples(shiny, shadow_filter_radius=1)
    torch.testing.assert_close(
        mixed[up], samples(shiny, shadow_filter_radius=1, filtered_area_samples=16)[up], rtol=1e-5, atol=1e-6
    )
    torch.testing.assert_close(
        mixed[~up], samples(shiny, shadow_filter_radius=1, area_samples=1)[~up], rtol=1e-5, atol=1e-6
    )
    assert not torch.allclose(mixed[up], samples(shiny, shadow_filter_radius=1, area_samples=1)[up])


@pytest.fixture(scope="module")
def leaves(tmp_path_factory) -> Relighter:
    """The leaves scene (cut-out leaf shadows on a floor) at 96 x 72 under its sphere light alone,
    four times brighter so that the floor's light spans [0, 1]."""
    directory = tmp_path_factory.mktemp("leaves")
    bundled = SCENES["leaves"]
    scene = load_scene(bundled.write(directory / "scene"), width=SIZE, height=72)
    layer = bake_direct(scene, find_camera(scene, bundled.camera), directory / "cache", "leaves", 1, 1)
    relighter = open_relighter(layer)
    relighter.set_lights(
        [
            dataclasses.replace(light, intensity=4.0 * light.intensity)
            for light in relighter.lights
            if light.kind is LightKind.SPHERE
        ]
    )
    return relighter


def test_sphere_light_ratio_and_filtered_visibility(leaves, monkeypatch):
    # Measured: 4 samples plain 42.88, with the ratio 42.88 (the cap's samples already estimate the
    # unshadowed term well: the noise is the leaves' shadows); 1 sample plain 36.1, with the ratio
    # 36.2, filtered r = 1 39.0; 256 with the ratio 65.0 dB. The closed form pays for the sphere
    # by what it enables: one filtered sample per matte point (LightStages.sample_groups).
    lights = leaves.lights
    truth = plain(leaves, lights, 256, monkeypatch)
    ratio4, plain4 = psnr(render(leaves, lights, 4), truth), psnr(plain(leaves, lights, 4, monkeypatch), truth)
    assert ratio4 >= 42.5 and ratio4 >= plain4 - 0.05
    ratio1 = psnr(render(leaves, lights, 1), truth)
    assert ratio1 >= psnr(plain(leaves, lights, 1, monkeypatch), truth) - 0.05
    assert psnr(render(leaves, lights, 1, radius=1), truth) >= ratio1 + 2.4
    assert psnr(render(leaves, lights, 256), truth) >= 60.0  # the same limit as plain Monte Carlo
