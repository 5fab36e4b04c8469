"""A lights layer of only the changes: composed over the shot it gives the edited rig exactly."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from pxr import Sdf, Usd

from pipeline.scene.lights import read_lights
from pipeline.scenes.registry import SCENES
from relight_torch.lights.light import Light, LightKind, Shaping
from relight_torch.lights.overrides import light_overrides_layer, write_light_overrides
from relight_torch.stage import open_stage
from test_lights_usd import assert_same

DEFAULT = Usd.TimeCode.Default()


@pytest.fixture(scope="module")
def shot(tmp_path_factory) -> tuple[str, list[Light]]:
    directory = tmp_path_factory.mktemp("shot")
    path = SCENES["glossy"].write(directory)
    return str(path), read_lights(open_stage(path), DEFAULT)


def moved(light: Light, offset: tuple[float, float, float]) -> Light:
    world = light.world_from_light.copy()
    world[:3, 3] += offset
    return dataclasses.replace(light, world_from_light=world)


def composed(shot_path: str, layer) -> list[Light]:
    return read_lights(open_stage(shot_path, layer), DEFAULT)


def test_edits_compose_to_the_edited_rig(shot, tmp_path):
    path, before = shot
    first, *rest = before
    new_light = Light(
        path="/World/Lights/NewFill", kind=LightKind.SPHERE, intensity=3.0, radius=0.25, light_group="fill"
    )
    after = [
        dataclasses.replace(moved(first, (0.5, -0.25, 1.0)), intensity=first.intensity * 2, shaping=Shaping()),
        *rest[:-1],
        new_light,
    ]
    layer = tmp_path / "edits.usda"
    write_light_overrides(layer, before, after)
    result = {light.path: light for light in composed(path, layer)}
    assert set(result) == {light.path for light in after}
    for light in after:
        assert_same(result[light.path], light, light.path)


def test_only_changed_attributes_are_authored(shot):
    _, before = shot
    light = before[0]
    after = [dataclasses.replace(light, color=(1.0, 0.5, 0.25)), *before[1:]]
    layer = light_overrides_layer(before, after)
    spec = layer.GetPrimAtPath(light.path)
    assert spec.specifier == Sdf.SpecifierOver
    assert list(spec.properties.keys()) == ["inputs:color"]
    assert spec.GetInfo("apiSchemas") == Sdf.TokenListOp()  # unchanged: not authored
    assert [p.path for p in layer.rootPrims] == [Sdf.Path(light.path).GetPrefixes()[0]]
    assert layer.rootPrims[0].specifier == Sdf.SpecifierOver


def test_no_change_is_an_empty_layer(shot):
    _, before = shot
    layer = light_overrides_layer(before, list(before))
    assert not layer.rootPrims


def test_moved_light_lands_where_it_was_put(shot, tmp_path):
    path, before = shot
    after = [moved(before[0], (0.0, 2.0, 0.0)), *before[1:]]
    write_light_overrides(tmp_path / "move.usda", before, after)
    result = composed(path, tmp_path / "move.usda")
    np.testing.assert_array_equal(result[0].world_from_light, after[0].world_from_light)


def test_duplicate_paths_are_refused(shot):
    _, before = shot
    with pytest.raises(ValueError, match=f"{before[0].path}: two lights of the after rig"):
        light_overrides_layer(before, [before[0], before[0]])
