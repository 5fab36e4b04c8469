"""The relighter's memory budget (`RelightSettings.memory_budget`): over it, the transports of the
lights edited longest ago are dropped, a light whose transport does not fit is shaded tile by tile
without keeping it, the unit images of the lights edited longest ago are folded into one sum, and
unit images go to half precision. The image stays the unbounded relighter's (to float rounding; to
half-precision rounding once images are halved), a colour edit still shades nothing, and a shaping
edit of a light whose transport was dropped traces it again.

Shares the Cornell-box bake and lights of tests/test_relighter_cache_counters.py.
"""

from __future__ import annotations

import dataclasses
import os

import pytest
import torch

from pipeline import cli
from pipeline.bake.direct.bake import bake_direct
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES
from pipeline.serve.session import Session
from relight_torch.direct.relighter import Relighter
from relight_torch.direct.settings import MEMORY_BUDGET_FRACTION, RelightSettings, default_memory_budget
from relight_torch.io.exr import read_exr
from test_relighter_cache_counters import SETTINGS, assert_same_image, baked, low_rect, moved, spot  # noqa: F401

FILTERED = dataclasses.replace(SETTINGS, shadow_filter_radius=1)  # the rect light's visibility filtered


def _relighter(baked: Relighter, budget: int | None, settings: RelightSettings = SETTINGS) -> Relighter:
    relighter = Relighter(
        baked.gbuffer,
        baked.visibility,
        baked.supersampling,
        baked.exposure_scale,
        dataclasses.replace(settings, memory_budget=budget),
    )
    relighter.set_lights(baked.lights + [spot(), low_rect()])
    return relighter


def _image_bytes(relighter: Relighter, element_size: int = 4) -> int:
    return len(relighter.lights) * 2 * relighter.gbuffer.num_samples * 3 * element_size


def _transports(relighter: Relighter) -> dict[str, bool]:
    return {path: state.transports is not None for path, state in relighter._lights.items()}


def test_the_oldest_transports_are_dropped(baked):
    unbounded = _relighter(baked, 1 << 40)
    expected = unbounded.render()
    largest = max(sum(t.num_bytes for t in state.transports) for state in unbounded._lights.values())
    budget = _image_bytes(unbounded) + largest
    relighter = _relighter(baked, budget)
    assert_same_image(relighter.render(), expected)
    assert relighter.cache_bytes() <= budget < unbounded.cache_bytes()
    kept = _transports(relighter)
    assert any(kept.values()) and not all(kept.values())
    assert not relighter._budget.half_images


def test_a_colour_edit_under_the_budget_shades_nothing(baked):
    unbounded = _relighter(baked, 1 << 40)
    relighter = _relighter(baked, _image_bytes(unbounded))
    relighter.render()
    before = dict(relighter.counters)
    light = dataclasses.replace(relighter.lights[0], color=(0.2, 0.5, 1.0))
    relighter.set_light(light)
    unbounded.set_light(light)
    assert_same_image(relighter.render(), unbounded.render())
    assert dict(relighter.counters) == before


def test_a_shaping_edit_of_a_dropped_light_traces_it_again(baked):
    unbounded = _relighter(baked, 1 << 40)
    relighter = _relighter(baked, _image_bytes(unbounded))  # room for the images only: nothing kept
    relighter.render()
    assert not any(_transports(relighter).values())
    light = next(light for light in relighter.lights if light.path == "/Test/Spot")
    edited = dataclasses.replace(light, shaping=dataclasses.replace(light.shaping, cone_angle=15.0))
    visibility = relighter.counters["visibility"]
    for r in (relighter, unbounded):
        r.set_light(edited)
    assert_same_image(relighter.render(), unbounded.render())
    assert relighter.counters["visibility"] == visibility + 1


@pytest.mark.parametrize("settings", [SETTINGS, FILTERED], ids=["unfiltered", "filtered"])
def test_tiles_shaded_without_their_transport_match(baked, settings):
    """Images made tile by tile (no transport fits) equal those of the kept transports, the
    filtered visibility of the rect light's ratio estimator included."""
    unbounded = _relighter(baked, 1 << 40, settings)
    relighter = _relighter(baked, _image_bytes(unbounded), settings)
    assert_same_image(relighter.render(), unbounded.render())
    assert relighter.cache_bytes() == _image_bytes(unbounded)
    for r in (relighter, unbounded):
        r.set_light(moved(next(light for light in r.lights if light.path == "/Test/LowRect")))
    assert_same_image(relighter.render(), unbounded.render())


def _folded(relighter: Relighter) -> list[str]:
    return [path for path, state in relighter._lights.items() if state.folded]


def test_a_tiny_budget_folds_the_lights_edited_longest_ago(baked):
    """Room for one light's unit images and the folded sum: every other light is folded, the
    frame is the same, and edits of folded lights (colour, move, removal) give the unbounded
    relighter's frames, each unfolding only the light it edits."""
    unbounded = _relighter(baked, 1 << 40)
    expected = unbounded.render()
    per_light = _image_bytes(unbounded) // len(unbounded.lights)
    budget = per_light + per_light // 2  # (2, N, 3) unit images and the (N, 3) folded sum
    relighter = _relighter(baked, budget)
    assert_same_image(relighter.render(), expected)
    assert relighter.held_bytes() <= budget and not relighter._budget.half_images
    folded = _folded(relighter)
    assert len(folded) == len(relighter.lights) - 1 and relighter._active not in folded
    edits = [
        (folded[0], lambda light: dataclasses.replace(light, color=(0.2, 0.5, 1.0))),
        (folded[1], moved),
    ]
    for path, edit in edits:
        for r in (relighter, unbounded):
            r.set_light(edit(next(light for light in r.lights if light.path == path)))
        assert_same_image(relighter.render(), unbounded.render())
        assert relighter.held_bytes() <= budget
        assert path not in _folded(relighter) and len(_folded(relighter)) == len(relighter.lights) - 1
    removed = _folded(relighter)[0]
    for r in (relighter, unbounded):
        r.remove_light(removed)
    assert_same_image(relighter.render(), unbounded.render())
    groups, expected_groups = relighter.light_group_images(), unbounded.light_group_images()
    assert groups.keys() == expected_groups.keys()
    for name, image in groups.items():
        assert_same_image(image, expected_groups[name])


def test_half_precision_images_when_even_they_do_not_fit(baked):
    unbounded = _relighter(baked, 1 << 40)
    expected = unbounded.render()
    relighter = _relighter(baked, 0)
    image = relighter.render()
    # Every light but the active one folded; its images, the last ones held, in half precision.
    assert relighter._budget.half_images and len(_folded(relighter)) == len(relighter.lights) - 1
    num_samples = relighter.gbuffer.num_samples
    assert relighter.cache_bytes() == num_samples * 3 * 4 + _image_bytes(relighter, 2) // len(relighter.lights)
    assert_same_image(image, expected)  # this frame was made before the budget was applied
    # float16 keeps 11 significant bits: a relative rounding of 2^-11 of the active light's image.
    light = relighter.lights[-1]
    for r in (relighter, unbounded):
        r.set_light(dataclasses.replace(light, intensity=2.0 * light.intensity))
    expected = unbounded.render()
    torch.testing.assert_close(relighter.render(), expected, rtol=2e-3, atol=2e-3 * float(expected.abs().max()))


def test_render_memory_budget_option(tmp_path, capsys):
    bundled = SCENES["cornell_box"]
    scene = load_scene(bundled.write(tmp_path / "scene"), width=16, height=16)
    layer = bake_direct(scene, find_camera(scene, bundled.camera), tmp_path / "cache", "cornell_box")
    default, small = tmp_path / "default.exr", tmp_path / "small.exr"
    assert cli.main(["render", str(layer), "-o", str(default)]) == 0
    assert cli.main(["render", str(layer), "-o", str(small), "--memory-budget", "0"]) == 0
    a, b = (read_exr(path)[0]["R"] for path in (default, small))
    assert abs(a - b).max() <= 2e-3 * abs(a).max()
    assert cli.main(["render", str(layer), "-o", str(small), "--memory-budget", "-1"]) == 2
    assert "--memory-budget" in capsys.readouterr().err
    # `relight serve` takes the same option, checked before it listens, and hands it to the relighter.
    assert cli.main(["serve", str(layer), "--memory-budget", "-1"]) == 2
    assert "--memory-budget" in capsys.readouterr().err
    session = Session.open(layer, out_dir=tmp_path, settings=RelightSettings(memory_budget=12345))
    try:
        assert session._relighter.memory_budget == 12345
    finally:
        session.close()


def test_default_budget_is_a_share_of_the_machine(baked):
    physical = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    assert _relighter(baked, None).memory_budget == default_memory_budget() == int(MEMORY_BUDGET_FRACTION * physical)
    with pytest.raises(ValueError, match="memory_budget"):
        _relighter(baked, -1)
