"""Light-group AOVs: `relight render --aov lightgroups` and `Relighter.light_group_images()`.

The Cornell box is relit with its ceiling lamp plus two sphere lights sharing the group
'key.rim' (a name EXR layers cannot hold as is: it must come out as 'key_rim'). The EXR, read
back with OpenImageIO, holds R, G, B and one layer per group, which sum to the beauty; an
intensity edit of every light of one group scales that group's image and nothing else, and
runs no visibility or shading pass. The indirect methods (transfer, gather) split each group
into direct and indirect layers that still sum to the beauty.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import OpenImageIO as oiio
import pytest

from pipeline import cli
from pipeline.bake.direct.bake import bake_direct
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES
from relight_torch.direct.loading import shot_lights
from relight_torch.direct.relighter import open_relighter
from relight_torch.direct.rig import light_group
from relight_torch.direct.settings import RelightSettings
from relight_torch.io.exr import exr_layer_names
from relight_torch.lights.light import Light, LightKind
from relight_torch.lights.usd import write_lights_layer

SIZE = 16
SETTINGS = RelightSettings(area_samples=4)


def _sphere(name: str, position: tuple[float, float, float], color: tuple[float, float, float]) -> Light:
    world_from_light = np.eye(4)
    world_from_light[:3, 3] = position
    return Light(
        f"/World/Lights/{name}",
        LightKind.SPHERE,
        world_from_light,
        intensity=4.0,
        radius=30.0,
        color=color,
        light_group="key.rim",
    )


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    directory = tmp_path_factory.mktemp("groups")
    shot = SCENES["cornell_box"].write(directory / "scene")
    scene = load_scene(shot, width=SIZE, height=SIZE)
    cache = bake_direct(
        scene,
        find_camera(scene, SCENES["cornell_box"].camera),
        directory / "cache",
        "cornell_box",
        supersampling=1,
        texture_samples=1,
    )
    lights = [
        *scene.lights,
        _sphere("KeyA", (150.0, 300.0, 200.0), (1.0, 0.5, 0.2)),
        _sphere("KeyB", (400.0, 200.0, 150.0), (0.2, 0.6, 1.0)),
    ]
    layer = directory / "groups.usda"
    write_lights_layer(layer, lights)
    return cache, layer


def test_layer_names_are_sanitised_and_distinct():
    assert exr_layer_names(["key.rim", "key rim", "Fill", "", "ceiling"], taken=("ceiling",)) == [
        "key_rim",
        "key_rim_2",
        "Fill",
        "_",
        "ceiling_2",
    ]


def test_render_writes_group_layers_that_sum_to_the_beauty(baked, tmp_path):
    cache, layer = baked
    out = tmp_path / "groups.exr"
    assert cli.main(["render", str(cache), "--lights", str(layer), "-o", str(out), "--aov", "lightgroups"]) == 0
    image = oiio.ImageBuf(str(out))
    names = list(image.spec().channelnames)
    assert sorted(names) == sorted(
        ["R", "G", "B", "CeilingLight.R", "CeilingLight.G", "CeilingLight.B", "key_rim.R", "key_rim.G", "key_rim.B"]
    )
    pixels = {name: image.get_pixels(oiio.FLOAT)[..., i] for i, name in enumerate(names)}
    for channel in "RGB":
        beauty = pixels[channel]
        layers = pixels[f"CeilingLight.{channel}"] + pixels[f"key_rim.{channel}"]
        assert np.abs(layers - beauty).max() <= 1e-6 * beauty.max()
        assert pixels[f"key_rim.{channel}"].max() > 0.01 * beauty.max()


def test_group_intensity_edit_is_a_rescale_of_its_layer(baked):
    cache, layer = baked
    relighter = open_relighter(cache, lights_layer=layer, settings=SETTINGS)
    before = relighter.light_group_images()
    counters = dict(relighter.counters)
    for light in relighter.lights:
        if light_group(light) == "key.rim":
            relighter.set_light(dataclasses.replace(light, intensity=2.5 * light.intensity))
    after = relighter.light_group_images()
    assert dict(relighter.counters) == counters
    assert list(after) == ["CeilingLight", "key.rim"]
    np.testing.assert_allclose(after["key.rim"].numpy(), 2.5 * before["key.rim"].numpy(), rtol=1e-6, atol=1e-9)
    assert np.array_equal(after["CeilingLight"].numpy(), before["CeilingLight"].numpy())
    edited = [
        dataclasses.replace(light, intensity=2.5 * light.intensity) if light_group(light) == "key.rim" else light
        for light in shot_lights(relighter.description, layer)
    ]
    fresh = open_relighter(cache, settings=SETTINGS)
    fresh.set_lights(edited)
    np.testing.assert_allclose(sum(after.values()).numpy(), fresh.render().numpy(), rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize(
    "method_options",
    [
        ["--method", "transfer", "--gathers", "256", "--coefficients", "30"],
        ["--method", "gather", "--directions", "64", "--clusters", "8"],
    ],
    ids=["transfer", "gather"],
)
def test_indirect_render_splits_each_group_into_direct_and_indirect(baked, tmp_path, method_options):
    _, layer = baked
    shot = SCENES["cornell_box"].write(tmp_path / "scene")
    out = tmp_path / "cache"
    assert (
        cli.main(
            [
                "bake",
                str(shot),
                "--camera",
                SCENES["cornell_box"].camera,
                "--out",
                str(out),
                "--width",
                str(SIZE),
                "--height",
                str(SIZE),
                "--supersampling",
                "1",
                *method_options,
            ]
        )
        == 0
    )
    exr = tmp_path / "groups.exr"
    assert (
        cli.main(
            [
                "render",
                str(out / "cornell_box.relight.usda"),
                "--lights",
                str(layer),
                "-o",
                str(exr),
                "--aov",
                "lightgroups",
            ]
        )
        == 0
    )
    image = oiio.ImageBuf(str(exr))
    names = list(image.spec().channelnames)
    layers = [f"{group}_{part}" for group in ("CeilingLight", "key_rim") for part in ("direct", "indirect")]
    assert sorted(names) == sorted(["R", "G", "B"] + [f"{name}.{c}" for name in layers for c in "RGB"])
    pixels = {name: image.get_pixels(oiio.FLOAT)[..., i] for i, name in enumerate(names)}
    for channel in "RGB":
        beauty = pixels[channel]
        total = sum(pixels[f"{name}.{channel}"] for name in layers)
        assert np.abs(total - beauty).max() <= 1e-5 * beauty.max()
        assert pixels[f"key_rim_indirect.{channel}"].max() > 1e-3 * beauty.max()
