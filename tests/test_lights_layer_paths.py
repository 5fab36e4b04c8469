"""A lights layer cannot make the relighter read files outside the shot's and the layer's folders
without saying so: each such sublayer, reference, payload or asset input is one warning line naming
the layer, the prim and the file (docs/ERRORS.md)."""

from __future__ import annotations

from pathlib import Path

import pytest

from fuzz_support import bake_all, run_relight
from relight_torch.stage import outside_reads


@pytest.fixture(scope="module")
def direct(tmp_path_factory) -> Path:
    return bake_all(tmp_path_factory.mktemp("paths"), ("direct",))["direct"]


def _layers(root: Path) -> tuple[Path, Path, Path]:
    """(shot, lights layer, a folder outside both) with a lights layer naming files in and out."""
    shot = root / "shot" / "shot.usda"
    shot.parent.mkdir()
    shot.write_text("#usda 1.0\n")
    lights, elsewhere = root / "lights" / "lights.usda", root / "elsewhere"
    lights.parent.mkdir()
    elsewhere.mkdir()
    (elsewhere / "far.usda").write_text(
        '#usda 1.0\nover "World"\n{\n    over "Lights"\n    {\n        over "Far"\n        {\n'
        "            asset inputs:texture:file = @./sky.exr@\n        }\n    }\n}\n"
    )
    (lights.parent / "near.usda").write_text("#usda 1.0\n")
    lights.write_text(
        "#usda 1.0\n(\n    subLayers = [@../elsewhere/far.usda@, @./near.usda@]\n)\n"
        'over "World"\n{\n    over "Lights"\n    {\n'
        '        def RectLight "Key"\n        {\n            asset inputs:texture:file = @../shot/tex/key.exr@\n'
        "            asset relight:barzel:cookie:file = @/etc/hostname@\n        }\n"
        '        def Xform "Rig" (prepend references = @../elsewhere/rig.usda@</Rig>)\n        {\n        }\n'
        "    }\n}\n"
    )
    return shot, lights, elsewhere


def test_files_outside_both_folders_are_listed_once_each(tmp_path):
    shot, lights, elsewhere = _layers(tmp_path)
    lines = outside_reads(shot, lights)
    tail = f", outside the shot's folder {shot.parent} and the lights layer's folder {lights.parent}; read all the same"
    assert lines == [
        f"{lights}: subLayers names {elsewhere / 'far.usda'}{tail}",
        f"{lights}: /World/Lights/Key: relight:barzel:cookie:file names /etc/hostname{tail}",
        f"{lights}: /World/Lights/Rig: references names {elsewhere / 'rig.usda'}{tail}",
        # found in the sublayer outside: its own texture, beside it
        f"{elsewhere / 'far.usda'}: /World/Lights/Far: inputs:texture:file names {elsewhere / 'sky.exr'}{tail}",
    ]


def test_a_lights_layer_within_the_folders_says_nothing(tmp_path):
    shot, lights, _ = _layers(tmp_path)
    lights.write_text(
        "#usda 1.0\n(\n    subLayers = [@./near.usda@]\n)\n"
        'over "World"\n{\n    def DomeLight "Sky"\n    {\n'
        "        asset inputs:texture:file = @../shot/sky.exr@\n    }\n}\n"
    )
    assert outside_reads(shot, lights) == []


def test_relight_render_warns_in_one_line_naming_the_prim_and_file(direct, tmp_path):
    outside = tmp_path / "elsewhere" / "extra.usda"
    outside.parent.mkdir()
    outside.write_text("#usda 1.0\n")
    lights = tmp_path / "lights.usda"
    lights.write_text(
        '#usda 1.0\nover "World"\n{\n    over "Lights"\n    {\n'
        '        def Xform "Rig" (prepend references = @./elsewhere/extra.usda@)\n        {\n        }\n'
        "    }\n}\n"
    )
    status, stderr = run_relight(["render", str(direct), "--lights", str(lights), "-o", str(tmp_path / "in.exr")])
    assert status == 0 and "relight: WARNING" not in stderr, stderr  # under the lights layer's folder
    lights.replace(tmp_path / "elsewhere" / "lights.usda")
    moved = tmp_path / "rig" / "lights.usda"
    moved.parent.mkdir()
    moved.write_text(
        '#usda 1.0\nover "World"\n{\n    over "Lights"\n    {\n'
        '        def Xform "Rig" (prepend references = @../elsewhere/extra.usda@)\n        {\n        }\n'
        "    }\n}\n"
    )
    status, stderr = run_relight(["render", str(direct), "--lights", str(moved), "-o", str(tmp_path / "out.exr")])
    warnings = [line for line in stderr.splitlines() if line.startswith("relight: WARNING: ")]
    assert status == 0 and len(warnings) == 1, stderr
    assert warnings[0].startswith(f"relight: WARNING: {moved}: /World/Lights/Rig: references names {outside}, "), stderr
