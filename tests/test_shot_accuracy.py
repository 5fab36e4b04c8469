"""The shot-cache benchmark's parts: the error split by pixel class, the merged tables, the edit kinds timed."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from pxr import Sdf

from pipeline.bake.methods import bake_method
from pipeline.bake.transfer.bake import TransferSettings
from pipeline.benchmarks import shot_accuracy
from pipeline.benchmarks.shot_accuracy import EDGE, EDIT_KINDS, NO_DOME, NOT_SUPPORTED, TEXTURED, EditRow, SceneRow
from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import glossy
from relight_torch import open_cache
from relight_torch.cache.layer import read_cache_layer
from relight_torch.direct.loading import shot_lights
from relight_torch.lights.light import LightKind


def test_error_split_gives_each_class_its_share_of_the_squared_error():
    reference = np.full((2, 2, 3), 0.5)
    image = reference.copy()
    image[0, 0] += 0.1  # textured: squared error 0.01 per channel
    image[1, 1] += 0.2  # edge: 0.04
    image[0, 1] = 3.0  # plain, both clamped to [0, 1] as PSNR measures: 0.25
    classes = np.array([[TEXTURED, 2], [2, EDGE]])
    pixels, textured_share, textured_db, edge_share = shot_accuracy.error_split(image, reference, classes)
    assert pixels == 0.25
    assert textured_share == pytest.approx(0.01 / 0.30)
    assert textured_db == pytest.approx(20.0)
    assert edge_share == pytest.approx(0.04 / 0.30)
    assert math.isnan(shot_accuracy.error_split(image, reference, np.full((2, 2), 2))[2])


def _edit_row(scene: str, edit: str, psnr_db: float) -> EditRow:
    """A row measured before the reference noise and pixel-class columns existed (those are nan)."""
    return EditRow(scene, edit, 8, 6, 4, psnr_db, math.nan, math.nan, 0.01, 0.98, 0.02, 0.95, *([math.nan] * 4))


def test_a_run_replaces_its_scenes_rows_and_keeps_the_others(tmp_path):
    path = tmp_path / "shot.csv"
    shot_accuracy._write_csv(path, EditRow, [_edit_row("a", "shot", 30.0), _edit_row("b", "shot", 31.0)])
    merged = shot_accuracy._merged(path, EditRow, [_edit_row("b", "move", 33.0)])
    assert [(r.scene, r.edit, r.psnr_db) for r in merged] == [("a", "shot", 30.0), ("b", "move", 33.0)]
    assert math.isnan(merged[0].textured_psnr_db)
    path.write_text("scene,edit,psnr_db\na,shot,30\n")  # an older table's columns: replaced whole
    assert shot_accuracy._merged(path, EditRow, [_edit_row("b", "move", 33.0)]) == [_edit_row("b", "move", 33.0)]


def test_summary_names_what_was_not_measured_in_words(tmp_path):
    scene = SceneRow(
        "a",
        8,
        6,
        "direct",
        0,
        "{}",
        30.0,
        30.0,
        1.0,
        1.0,
        0.1,
        "16x12",
        *(["5"] * 4),
        NO_DOME,
        NOT_SUPPORTED,
        "python -m pipeline.benchmarks.shot_accuracy a",
    )
    shot_accuracy._write(tmp_path, [_edit_row("a", "shot", 30.0)], [scene], "python -m ... a")
    summary = (tmp_path / "summary.md").read_text()
    assert "| a | shot | 8x6 | 4 | 30.00 | not measured | not measured | 0.0100 | 0.980 |" in summary
    assert "| 16x12 | 5 | 5 | 5 | 5 | no dome | not supported |" in summary
    assert "nan" not in summary


@pytest.fixture(scope="module")
def glossy_dome(tmp_path_factory):
    """The glossy+dome shot and a direct cache of glossy at 16 x 12."""
    work = tmp_path_factory.mktemp("glossy_dome")
    shot = shot_accuracy.shot_of("glossy+dome", work)
    scene = load_scene(shot.path, width=16, height=12)
    layer = bake_method("direct").bake(
        scene, find_camera(scene, shot.camera), work / "cache", "glossy", 1, 1, None, None
    )
    return shot, layer


def test_glossy_dome_relights_the_glossy_bake_under_its_layer(glossy_dome):
    shot, _ = glossy_dome
    assert (shot.name, shot.base, shot.path.name) == ("glossy+dome", "glossy", "glossy.usda")
    assert list(shot.edits) == ["shot", "move", "reaim_spot", "colour_shaping", "rotate", "new_light"]
    assert shot.edits["shot"].name == "glossy.lights.dome.usda"


def test_every_edit_kind_is_timed_or_named(glossy_dome):
    shot, layer = glossy_dome
    timings = shot_accuracy.edit_timings(layer, shot, repeats=1)
    assert list(timings) == list(EDIT_KINDS)
    # A dome to turn, and materials the direct relighter edits.
    assert all(isinstance(timings[kind], float) and timings[kind] > 0 for kind in EDIT_KINDS)
    no_dome = dataclasses.replace(shot, edits={"shot": None, "new_light": shot.edits["new_light"]})
    assert shot_accuracy.edit_timings(layer, no_dome, repeats=1)["dome turn"] == NO_DOME


@pytest.mark.slow
def test_a_dome_added_by_a_lights_layer_reaches_the_transfer_caches_indirect_light(tmp_path):
    # The dome is not in the baked shot: its gather light is made at relight time like any light's.
    # Against the path tracer's one-bounce indirect light the transfer keeps ~0.85 of it on the
    # glossy scene, as for the shot's own sphere lights: the light the metals reflect onto other
    # surfaces (diffuse gathers do not carry it) and the normal-mapped floor's share are the gap.
    shot = shot_accuracy.shot_of("glossy+dome", tmp_path)
    only_dome = Sdf.Layer.CreateAnonymous(".usda")
    for path in (glossy.KEY, glossy.SPOT):
        Sdf.CreatePrimInLayer(only_dome, path).active = False
    only_dome.subLayerPaths.append(f"./{shot.edits['shot'].name}")
    layer_path = tmp_path / "glossy.lights.only_dome.usda"
    only_dome.Export(str(layer_path))
    scene = load_scene(shot.path, width=24, height=18)
    settings = TransferSettings(num_gathers=1024, num_coefficients=100)
    layer = bake_method("transfer").bake(
        scene, find_camera(scene, shot.camera), tmp_path / "cache", "glossy", 1, 1, None, settings
    )
    relighter = open_cache(layer)
    relighter.set_lights(shot_lights(read_cache_layer(layer), layer_path))
    assert [light.kind for light in relighter.lights] == [LightKind.DOME]
    indirect = relighter.indirect_image().numpy()
    lit = load_scene(shot.path, lights_layer=layer_path, width=24, height=18)
    camera = find_camera(lit, shot.camera)
    one, zero = (PathTracer(lit, ReferenceSettings(spp=32, max_bounces=b)).render(camera).mean for b in (1, 0))
    assert 0.7 < indirect.mean() / (one - zero).mean() < 1.05
