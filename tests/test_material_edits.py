"""Material edits in the direct relighter (`Relighter.edit_material`, `relight_torch.material_edits`).

After each kind of edit, of a warm relighter, the render equals a fresh relighter's whose G-buffer
holds the edited materials (within 1e-6); a colour edit traces no shadow ray and re-shades only
the edited material's points; progressive frames after an edit end in that image; bad inputs are
one-line errors naming the input.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from pxr import Gf, Sdf

from cache_support import bake_bundled
from pipeline import cli
from pipeline.scenes import SCENES
from relight_torch import open_cache
from relight_torch.direct.relighter import Relighter
from relight_torch.direct.settings import RelightSettings
from relight_torch.errors import RelightError
from relight_torch.io.exr import read_rgb_exr
from relight_torch.lights.light import Light, LightKind
from relight_torch.material_edits import apply_material_edit
from relight_torch.progressive import progressive_frames
from relighter_support import matte_params, twin

TOLERANCE = 1e-6
EDITS = {
    "diffuse colour": {"diffuse_color": (0.1, 0.6, 0.2)},
    "metallic": {"metallic": 1.0, "diffuse_color": (0.9, 0.6, 0.3)},
    "specular workflow": {"use_specular_workflow": True, "specular_color": (0.3, 0.3, 0.9)},
    "roughness": {"roughness": 0.55},
    "glossy": {"roughness": 0.2},
    "clearcoat": {"clearcoat": 1.0, "clearcoat_roughness": 0.1},
    "emission": {"emissive_color": (0.5, 0.2, 0.1)},
}
COLOUR_EDITS = ("diffuse colour", "metallic", "specular workflow")
# The surface filter of visibility (shared pixel groups at matte points) and plain sampling.
SETTINGS = {"filtered": RelightSettings(shadow_filter_radius=2), "plain": RelightSettings(shadow_filter_radius=0)}


@pytest.fixture(scope="module")
def cornell(tmp_path_factory) -> str:
    return str(bake_bundled("cornell_box", tmp_path_factory.mktemp("material_edits"), supersampling=2))


def _dome() -> Light:
    """A textured dome: its transport keeps RGB lobes and its BRDF samples follow the materials."""
    texture = np.full((8, 16, 3), 0.05, np.float32)
    texture[2:4, 3:6] = (4.0, 3.0, 2.0)
    return Light("/World/TestDome", LightKind.DOME, np.eye(4), intensity=0.5, texture=texture)


def _largest_material(relighter: Relighter) -> int:
    return int(torch.mode(relighter.gbuffer.material_id).values)


def _fresh(relighter: Relighter) -> Relighter:
    """A relighter of the same points and shadows whose G-buffer holds `relighter`'s current materials."""
    return twin(relighter, relighter.gbuffer)


@pytest.mark.parametrize("settings", sorted(SETTINGS))
@pytest.mark.parametrize("edit", sorted(EDITS))
def test_an_edit_renders_as_a_fresh_relighter_of_the_edited_materials(cornell, edit, settings):
    relighter = open_cache(cornell, settings=SETTINGS[settings])
    relighter.set_light(_dome())
    before = relighter.render()
    material = _largest_material(relighter)
    relighter.edit_material(material, **EDITS[edit])
    after = relighter.render()
    assert float((after - before).abs().max()) > 1e-3  # the edit shows
    assert float((after - _fresh(relighter).render()).abs().max()) <= TOLERANCE


@pytest.mark.parametrize("edit", COLOUR_EDITS)
def test_a_colour_edit_traces_nothing_and_shades_only_its_material(cornell, edit):
    relighter = open_cache(cornell, settings=SETTINGS["filtered"])
    relighter.render()
    material = _largest_material(relighter)
    rows = relighter.gbuffer.material_id == material
    traced = relighter.counters["visibility"]
    relighter.edit_material(material, **EDITS[edit])
    pending = relighter.pending(None)
    relighter.render()
    assert relighter.counters["visibility"] == traced
    assert 0 < pending <= int(rows.sum()) * max(relighter.num_light_samples(light) for light in relighter.lights)


@pytest.mark.parametrize("edit", ["roughness", "glossy"])
def test_a_roughness_edit_traces_the_material_again(cornell, edit):
    """Within matte (or glossy) points only the material's points are traced again; a material
    made glossy changes how many samples its points take: every point is traced again."""
    relighter = open_cache(cornell, settings=SETTINGS["filtered"])
    relighter.render()
    traced = relighter.counters["visibility"]
    material = _largest_material(relighter)
    rows = int((relighter.gbuffer.material_id == material).sum())
    relighter.edit_material(material, **EDITS[edit])
    pending = relighter.pending(None)
    relighter.render()
    assert relighter.counters["visibility"] == traced + len(relighter.lights)
    samples = max(relighter.num_light_samples(light) for light in relighter.lights)
    if edit == "roughness":
        assert 0 < pending <= rows * samples
    else:
        assert pending >= relighter.gbuffer.num_samples * len(relighter.lights)


@pytest.mark.parametrize("edit", ["diffuse colour", "roughness"])
def test_progressive_frames_after_an_edit_end_in_the_edited_render(cornell, edit):
    progressive = open_cache(cornell)
    progressive.render()
    progressive.edit_material(_largest_material(progressive), **EDITS[edit])
    frames = list(progressive_frames(progressive, budget_ms=0.0, strides=(4, 2, 1)))
    assert [frame.stride for frame in frames] == [4, 2, 1, None]
    assert float((frames[-1].image - _fresh(progressive).render()).abs().max()) <= TOLERANCE
    assert frames[0].evaluated < progressive.gbuffer.num_samples * len(progressive.lights)


def test_edits_mid_refinement_end_in_the_last_edit(cornell):
    """A colour edit, one coarse frame, then a roughness edit and another colour: the stale points
    and colours of both are made again as they are shaded."""
    progressive = open_cache(cornell, settings=SETTINGS["filtered"])
    progressive.set_light(_dome())
    progressive.render()
    material = _largest_material(progressive)
    progressive.edit_material(material, diffuse_color=(0.1, 0.6, 0.2))
    frames = progressive_frames(progressive, budget_ms=0.0, strides=(4, 2, 1))
    assert next(frames).stride == 4
    progressive.edit_material(material, roughness=0.55)
    progressive.edit_material(material, specular_color=(0.2, 0.2, 0.6), use_specular_workflow=True)
    rest = list(frames)
    assert rest[0].stride == 4 and rest[-1].done
    assert float((rest[-1].image - _fresh(progressive).render()).abs().max()) <= TOLERANCE


def test_an_edit_of_a_material_out_of_view_changes_nothing(cornell):
    relighter = open_cache(cornell)
    image = relighter.render()
    edits = relighter.edits
    relighter.edit_material(int(relighter.gbuffer.material_id.max()) + 1, roughness=0.1)
    assert relighter.edits == edits
    assert torch.equal(relighter.render(), image)


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"roughnes": 0.2}, r"material 0: no input 'roughnes' \(UsdPreviewSurface inputs: diffuse_color"),
        ({"opacity": 0.5}, "material 0: opacity: opacity changes the shadows"),
        ({"diffuse_color": (0.1, 0.2)}, r"material 0: diffuse_color takes 3 numbers, got \(0.1, 0.2\)"),
        ({"roughness": (0.1, 0.2)}, "material 0: roughness takes one number"),
        ({}, "material 0: no input to edit"),
    ],
)
def test_bad_inputs_are_one_line_errors(values, message):
    params = matte_params(4)
    with pytest.raises(RelightError, match=message) as error:
        apply_material_edit(params, torch.zeros(4, dtype=torch.int32), 0, values)
    assert "\n" not in str(error.value)


def test_a_grey_value_sets_every_channel():
    params, rows = apply_material_edit(matte_params(4), torch.tensor([0, 1, 0, 1]), 1, {"diffuse_color": 0.25})
    assert rows.tolist() == [False, True, False, True]
    assert params.diffuse_color[1].tolist() == [0.25, 0.25, 0.25]
    assert params.diffuse_color[0].tolist() == [0.5, 0.5, 0.5]
    assert math.isclose(float(params.roughness[1]), 0.5)


def test_cuts_light_and_direct_light_follow_one_edit(tmp_path):
    from pipeline.benchmarks.tiny_caches import bake_tiny

    relighter = open_cache(bake_tiny(tmp_path, ("cuts",))["cuts"])
    assert relighter.material_edits
    material = int(torch.mode(relighter.direct.gbuffer.material_id).values)
    relighter.render()
    relighter.edit_material(material, diffuse_color=(0.1, 0.6, 0.2))
    assert relighter.params is relighter.direct.gbuffer.params
    direct = relighter.direct.render()
    assert float((direct - _fresh(relighter.direct).render()).abs().max()) <= TOLERANCE


def _materials_layer(path, opinions: dict[str, dict[str, object]]) -> str:
    """A USD layer of `over`s: prim path -> {attribute name: value} (a float3 for a tuple, else a float)."""
    layer = Sdf.Layer.CreateNew(str(path))
    for prim, attributes in opinions.items():
        spec = Sdf.CreatePrimInLayer(layer, prim)
        spec.specifier = Sdf.SpecifierOver
        for name, value in attributes.items():
            kind = Sdf.ValueTypeNames.Color3f if isinstance(value, tuple) else Sdf.ValueTypeNames.Float
            Sdf.AttributeSpec(spec, name, kind).default = Gf.Vec3f(*value) if isinstance(value, tuple) else value
    layer.Save()
    return str(path)


def _wall(relighter: Relighter) -> tuple[str, str]:
    """The largest material in view and its UsdPreviewSurface shader's prim path."""
    material = relighter.material_paths[_largest_material(relighter)]
    return material, f"{material}/PreviewSurface"


def test_a_material_is_edited_by_its_prim_path(cornell):
    by_id, by_path = open_cache(cornell), open_cache(cornell)
    material, _ = _wall(by_path)
    assert material.startswith("/")
    by_id.edit_material(_largest_material(by_id), diffuse_color=(0.1, 0.6, 0.2))
    by_path.edit_material(material, diffuse_color=(0.1, 0.6, 0.2))
    assert torch.equal(by_id.render(), by_path.render())
    with pytest.raises(RelightError, match=r"^no material /World/Nope in the cache \(its materials: "):
        by_path.edit_material("/World/Nope", roughness=0.5)


def test_render_applies_a_materials_layer(cornell, tmp_path):
    relighter = open_cache(cornell)
    material, shader = _wall(relighter)
    layer = _materials_layer(
        tmp_path / "looks.usda",
        {shader: {"inputs:diffuseColor": (0.1, 0.6, 0.2), "inputs:roughness": 0.3}},
    )
    out = tmp_path / "edited.exr"
    assert cli.main(["render", cornell, "--materials", layer, "-o", str(out)]) == 0
    relighter.edit_material(material, diffuse_color=(0.1, 0.6, 0.2), roughness=0.3)
    assert np.abs(read_rgb_exr(out) - relighter.render().numpy()).max() <= TOLERANCE


def test_a_materials_layer_is_read_at_the_baked_time(cornell, tmp_path):
    """An input with time samples only (no default) is read at the frame the bake read."""
    relighter = open_cache(cornell)
    material, shader = _wall(relighter)
    layer = Sdf.Layer.CreateNew(str(tmp_path / "animated.usda"))
    spec = Sdf.CreatePrimInLayer(layer, shader)
    attribute = Sdf.AttributeSpec(spec, "inputs:diffuseColor", Sdf.ValueTypeNames.Color3f)
    for frame, colour in ((1.0, (0.1, 0.6, 0.2)), (50.0, (0.9, 0.1, 0.1))):
        layer.SetTimeSample(attribute.path, frame, Gf.Vec3f(*colour))
    layer.Save()
    out = tmp_path / "edited.exr"
    assert cli.main(["render", cornell, "--materials", str(tmp_path / "animated.usda"), "-o", str(out)]) == 0
    relighter.edit_material(material, diffuse_color=(0.1, 0.6, 0.2))
    assert np.abs(read_rgb_exr(out) - relighter.render().numpy()).max() <= TOLERANCE


def test_one_layer_holds_light_and_material_edits(cornell, tmp_path):
    relighter = open_cache(cornell)
    material, shader = _wall(relighter)
    light = relighter.lights[0]
    opinions = {shader: {"inputs:diffuseColor": (0.1, 0.6, 0.2)}, light.path: {"inputs:intensity": 2 * light.intensity}}
    layer = _materials_layer(tmp_path / "edits.usda", opinions)
    out = tmp_path / "edited.exr"
    assert cli.main(["render", cornell, "--lights", layer, "--materials", layer, "-o", str(out)]) == 0
    relighter.edit_material(material, diffuse_color=(0.1, 0.6, 0.2))
    relighter.set_light(dataclasses.replace(light, intensity=2 * light.intensity))
    assert np.abs(read_rgb_exr(out) - relighter.render().numpy()).max() <= TOLERANCE


@pytest.mark.parametrize(
    ("opinions", "message"),
    [
        ({"/World/Nope": {"inputs:roughness": 0.3}}, "/World/Nope.inputs:roughness: gives no UsdPreviewSurface input"),
        ({"{shader}": {"inputs:roughnes": 0.3}}, ".inputs:roughnes: gives no UsdPreviewSurface input"),
        ({"{material}": {"inputs:roughness": 0.3}}, ".inputs:roughness: gives no UsdPreviewSurface input"),
        ({"{shader}": {"inputs:opacity": 0.3}}, "opacity changes the shadows"),
    ],
)
def test_a_bad_materials_layer_is_one_error_line(cornell, tmp_path, capsys, opinions, message):
    material, shader = _wall(open_cache(cornell))
    named = {"{shader}": shader, "{material}": material}
    layer = _materials_layer(
        tmp_path / "looks.usda", {named.get(prim, prim): values for prim, values in opinions.items()}
    )
    capsys.readouterr()
    out = tmp_path / "edited.exr"
    assert cli.main(["render", cornell, "--materials", layer, "-o", str(out)]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("relight: error: ") and message in error and len(error.splitlines()) == 1
    assert not out.exists()


def test_a_materials_layer_on_a_cache_without_material_edits_is_refused(tmp_path, capsys):
    from pipeline.benchmarks.tiny_caches import bake_tiny

    layer = bake_tiny(tmp_path, ("gather",))["gather"]
    looks = _materials_layer(tmp_path / "looks.usda", {"/World/Looks/Any": {"inputs:roughness": 0.3}})
    capsys.readouterr()
    assert cli.main(["render", str(layer), "--materials", looks, "-o", str(tmp_path / "out.exr")]) == 2
    error = capsys.readouterr().err.strip()
    assert "--materials:" in error and "bake it with --method direct or --method cuts" in error


def test_relit_material_edits_match_the_path_tracer_of_the_edited_look(cornell, tmp_path):
    """`relight render --materials` against `relight reference --materials` (direct light, 1,024
    spp): the edited frame is as close to the path tracer's render of the edited look as the
    unedited one is to the shot's (measured 48.7 and 40.8 dB, energy 1.016 and 1.021)."""
    relighter = open_cache(cornell)
    _, shader = _wall(relighter)
    looks = _materials_layer(
        tmp_path / "looks.usda", {shader: {"inputs:diffuseColor": (0.1, 0.6, 0.2), "inputs:roughness": 0.55}}
    )
    source = relighter.description.source
    size = ["--width", str(relighter.gbuffer.image_size[1] // 2), "--height", str(relighter.gbuffer.image_size[0] // 2)]
    scores = {}
    for name, extra in (("shot", []), ("edited", ["--materials", looks])):
        relit, reference = tmp_path / f"{name}.exr", tmp_path / f"{name}-reference.exr"
        assert cli.main(["render", cornell, "-o", str(relit), *extra]) == 0
        arguments = ["reference", source, "--camera", SCENES["cornell_box"].camera, *size, "--max-bounces", "0"]
        arguments += ["--spp", "1024"]
        assert cli.main([*arguments, "-o", str(reference), *extra]) == 0
        image, truth = read_rgb_exr(relit), read_rgb_exr(reference)
        scores[name] = (10 * math.log10(1.0 / float(np.mean((image - truth) ** 2))), float(image.mean() / truth.mean()))
    assert scores["edited"][0] >= max(40.0, scores["shot"][0] - 1.0)
    assert abs(scores["edited"][1] - 1.0) <= 0.03


def test_a_session_opens_with_a_materials_layer(cornell, tmp_path):
    from pipeline.serve.session import Session

    relighter = open_cache(cornell)
    material, shader = _wall(relighter)
    looks = _materials_layer(tmp_path / "looks.usda", {shader: {"inputs:diffuseColor": (0.1, 0.6, 0.2)}})
    session = Session.open(cornell, out_dir=tmp_path, materials_layer=looks)
    try:
        frame = list(session.frames())[-1]
    finally:
        session.close()
    relighter.edit_material(material, diffuse_color=(0.1, 0.6, 0.2))
    assert frame.final and np.abs(frame.image - relighter.render().numpy()).max() <= TOLERANCE


def test_material_edits_are_set_whole_over_the_baked_materials(cornell):
    """`set_material_edits`: the baked materials with exactly these edits; an empty set restores
    the baked frame (a session's undo)."""
    relighter = open_cache(cornell)
    baked = relighter.render()
    material, _ = _wall(relighter)
    relighter.set_material_edits({material: {"diffuse_color": (0.1, 0.6, 0.2), "roughness": 0.55}})
    edited = relighter.render()
    expected = open_cache(cornell)
    expected.edit_material(material, diffuse_color=(0.1, 0.6, 0.2), roughness=0.55)
    assert float((edited - expected.render()).abs().max()) <= TOLERANCE
    relighter.set_material_edits({material: {"roughness": 0.55}})
    expected = open_cache(cornell)
    expected.edit_material(material, roughness=0.55)
    assert float((relighter.render() - expected.render()).abs().max()) <= TOLERANCE
    relighter.set_material_edits({})
    assert float((relighter.render() - baked).abs().max()) <= TOLERANCE
