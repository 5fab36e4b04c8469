"""Generated bad lights layers and shots: each `relight render --lights` and `relight bake` either
refuses with one line naming the file, or renders (bakes) finite pixels; never a traceback or a hang.

Lights layers get odd attribute values (NaN, infinities, negative or zero sizes, values of the
wrong type), many lights, references to missing files and cycles of sublayers; shots get odd
points, counts, transforms and light values. Bounded example counts by default;
HYPOTHESIS_PROFILE=nightly runs many more (tests/fuzz_support.py).
"""

from __future__ import annotations

import dataclasses
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from fuzz_support import RENDER_SECONDS, assert_refused_or_finite, bake_all, bounded, quiet_main, render, tally
from pipeline.bake import shot as shot_module
from pipeline.bake.transfer import method as transfer_method
from relight_torch import open_cache
from relight_torch.io.exr import read_exr

LIGHT = "/World/Lights/CeilingLight"
_VALUES = ["nan", "inf", "-inf", "-1", "0", "1e-30", "1e30", "1e300", "3", "-1e30"]
# attribute -> its USD type in the lights layer
_ATTRIBUTES = {
    "inputs:intensity": "float",
    "inputs:exposure": "float",
    "inputs:width": "float",
    "inputs:height": "float",
    "inputs:radius": "float",
    "inputs:colorTemperature": "float",
    "inputs:diffuse": "float",
    "inputs:specular": "float",
    "inputs:shaping:cone:angle": "float",
    "inputs:shaping:cone:softness": "float",
    "inputs:shaping:focus": "float",
    "inputs:shadow:distance": "float",
    "inputs:shadow:falloff": "float",
    "inputs:shadow:falloffGamma": "float",
    "inputs:color": "color3f",
    "xformOp:translate": "double3",
    "xformOp:scale": "float3",
    "inputs:enableColorTemperature": "bool",
    "inputs:normalize": "bool",
    "inputs:texture:file": "asset",
}
_KINDS = ["SphereLight", "RectLight", "DiskLight", "DistantLight", "CylinderLight", "DomeLight"]


@pytest.fixture(scope="module")
def baked(tmp_path_factory) -> dict[str, Path]:
    return bake_all(tmp_path_factory.mktemp("stage_bakes"), ("direct", "transfer"))


def _value(data: st.DataObject, type_name: str) -> str:
    """A USD literal of `type_name`, odd more often than not (or of another type: `wrong`)."""
    if data.draw(st.integers(0, 9), label="wrong type?") == 0:
        return data.draw(st.sampled_from(['"text"', "[1, 2]", "(1, 2)", "@./missing.exr@", "true"]), label="wrong")
    scalar = data.draw(st.sampled_from(_VALUES), label="scalar")
    if type_name in ("color3f", "double3", "float3"):
        others = [data.draw(st.sampled_from(_VALUES), label="component") for _ in range(2)]
        return f"({scalar}, {others[0]}, {others[1]})"
    if type_name == "bool":
        return data.draw(st.sampled_from(["0", "1", "true", "false"]), label="bool")
    if type_name == "asset":
        return data.draw(
            st.sampled_from(["@./missing.exr@", "@@", "@/etc/hostname@", "@./lights.usda@"]), label="asset"
        )
    return scalar


def _declared(data: st.DataObject, name: str) -> str:
    """`type name = value`, the type sometimes not the attribute's schema type."""
    type_name = _ATTRIBUTES[name]
    declared = data.draw(st.sampled_from([type_name] * 4 + ["string", "int", "double", "token"]), label="type")
    if declared in ("string", "token"):
        value = data.draw(st.sampled_from(['"x"', '""', '"nan"']), label="text")
    elif declared == "int":
        value = data.draw(st.sampled_from(["-1", "0", "2147483647"]), label="int")
    elif declared == "double":
        value = data.draw(st.sampled_from(_VALUES), label="double")
    else:
        value = _value(data, type_name)
    return f"{declared} {name} = {value}"


def _lights_layer(data: st.DataObject, directory: Path) -> Path:
    """A lights layer of drawn edits over the shot's light, new lights, references and sublayers."""
    edits = data.draw(
        st.lists(st.sampled_from(sorted(_ATTRIBUTES)), min_size=0, max_size=4, unique=True), label="edited attributes"
    )
    body = "\n".join(f"            {_declared(data, name)}" for name in edits)
    new_lights = []
    for k in range(data.draw(st.sampled_from([0, 0, 1, 3, 12]), label="new lights")):
        kind = data.draw(st.sampled_from(_KINDS), label="kind")
        attributes = data.draw(
            st.lists(st.sampled_from(sorted(_ATTRIBUTES)), max_size=2, unique=True), label="new light attributes"
        )
        lines = "\n".join(f"            {_declared(data, name)}" for name in attributes)
        new_lights.append(f'        def {kind} "New{k}"\n        {{\n{lines}\n        }}')
    metadata = []
    structure = data.draw(
        st.sampled_from(
            ["none", "self cycle", "two-layer cycle", "missing sublayer", "missing reference", "reference to itself"]
        ),
        label="structure",
    )
    extra = ""
    if structure == "self cycle":
        metadata.append("subLayers = [@./lights.usda@]")
    elif structure == "two-layer cycle":
        metadata.append("subLayers = [@./other.usda@]")
        (directory / "other.usda").write_text("#usda 1.0\n(\n    subLayers = [@./lights.usda@]\n)\n")
    elif structure == "missing sublayer":
        metadata.append("subLayers = [@./missing.usda@]")
    elif structure == "missing reference":
        extra = '        def Xform "Ref" (references = @./missing.usda@</Thing>)\n        {\n        }\n'
    elif structure == "reference to itself":
        extra = '        def Xform "Ref" (references = @./lights.usda@</World>)\n        {\n        }\n'
    text = "#usda 1.0\n(\n    " + "\n    ".join(metadata) + "\n)\n"
    text += (
        'over "World"\n{\n    over "Lights"\n    {\n        over "CeilingLight"\n        {\n'
        f"{body}\n        }}\n" + "\n".join(new_lights) + "\n" + extra + "    }\n}\n"
    )
    path = directory / "lights.usda"
    path.write_text(text)
    return path


@pytest.mark.slow
@pytest.mark.parametrize("method", ["direct", "transfer"])
@given(data=st.data())
def test_bad_lights_layer_is_one_line_or_a_finite_render(baked, tmp_path, method, data):
    directory = Path(tempfile.mkdtemp(dir=tmp_path))
    try:
        layer = _lights_layer(data, directory)
        outcome = render(baked[method], directory / "out" / "relit.exr", "--lights", str(layer))
        assert_refused_or_finite(outcome, layer, directory, baked[method].parent.parent / "scene")
        tally("bad lights layer", method=method, refused=outcome.status != 0)
    finally:
        shutil.rmtree(directory)


@pytest.mark.parametrize("method", ["direct", "transfer"])
@pytest.mark.parametrize(
    "kind, declarations, named",
    [
        # Found by the nightly profile: OverflowError in the light's area (radius 1e300, a huge
        # cylinder) and in 2^exposure; inf pixels for a light moved to 1e30 or a diffuse of 1e300.
        ("SphereLight", ["double inputs:radius = 1e300"], "inputs:radius = 1e+300 (authored as double) overflows"),
        ("CylinderLight", ["float inputs:radius = 1e30", "float inputs:length = 1e30"], "inputs:length gives"),
        (
            "RectLight",
            ["double3 xformOp:translate = (1e30, 0, 0)", 'uniform token[] xformOpOrder = ["xformOp:translate"]'],
            "xformOp (world transform) puts the light at (1e+30, 0, 0)",
        ),
        ("SphereLight", ["double inputs:exposure = 1e30"], "inputs:exposure"),
        ("SphereLight", ["float inputs:diffuse = 1e30"], "emits 1e+30 nits"),
    ],
)
def test_a_light_beyond_float32_arithmetic_is_one_line(baked, tmp_path, method, kind, declarations, named):
    lines = "\n".join(f"            {line}" for line in declarations)
    layer = tmp_path / "lights.usda"
    layer.write_text(
        '#usda 1.0\nover "World"\n{\n    over "Lights"\n    {\n'
        f'        def {kind} "Huge"\n        {{\n{lines}\n        }}\n    }}\n}}\n'
    )
    outcome = render(baked[method], tmp_path / "out" / "relit.exr", "--lights", str(layer))
    assert outcome.status == 2 and f"{layer}: /World/Lights/Huge: " in outcome.error, outcome
    assert named in outcome.error, outcome.error


@pytest.mark.parametrize("method", ["direct", "transfer"])
def test_set_light_refuses_a_light_beyond_float32_arithmetic(baked, method):
    # Lights edited from Python are validated as lights read from USD are (an OverflowError at render before).
    relighter = open_cache(baked[method])
    before = relighter.render()
    key = next(light for light in relighter.lights if light.path == LIGHT)
    with pytest.raises(ValueError, match=f"^{LIGHT}: inputs:width gives a world-space size of 1e\\+300"):
        relighter.set_light(dataclasses.replace(key, width=1e300))
    assert torch.equal(relighter.render(), before)


WALL = "[(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)]"
SHOT = """#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = {meters}
)
def Xform "World"
{{
    def Mesh "Wall"
    {{
        int[] faceVertexCounts = {counts}
        int[] faceVertexIndices = {indices}
        point3f[] points = {points}
        double3 xformOp:scale = {scale}
        uniform token[] xformOpOrder = ["xformOp:scale"]
    }}
    def Camera "Camera"
    {{
        double3 xformOp:translate = {camera}
        float focalLength = {focal}
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }}
    def {kind} "Key"
    {{
        float inputs:intensity = {intensity}
        float inputs:radius = {radius}
        double3 xformOp:translate = {light}
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }}
}}
"""


def _odd(data: st.DataObject, label: str, usual: str) -> str:
    return data.draw(st.sampled_from([usual] * 3 + _VALUES), label=label)


def _shot(data: st.DataObject, directory: Path) -> Path:
    fields = {
        "meters": data.draw(st.sampled_from(["1", "0", "-1", "nan", "1e-30", "inf"]), label="metersPerUnit"),
        "counts": data.draw(
            st.sampled_from(["[4]", "[3, 3]", "[5]", "[0]", "[2147483647]", "[]", "[-4]"]), label="counts"
        ),
        "indices": data.draw(
            st.sampled_from(["[0, 1, 2, 3]", "[0, 1, 2, 0, 2, 3]", "[0, 1, 2, 9]", "[]", "[-1, 0, 1, 2]"]),
            label="indices",
        ),
        "points": data.draw(
            st.sampled_from(
                [
                    WALL,
                    "[]",
                    "[(nan, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0)]",
                    "[(1e30, -1e30, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)]",
                    "[(0, 0, 0), (0, 0, 0), (0, 0, 0), (0, 0, 0)]",
                ]
            ),
            label="points",
        ),
        "scale": data.draw(
            st.sampled_from(["(1, 1, 1)", "(0, 0, 0)", "(1, -1, 1)", "(nan, 1, 1)", "(1e30, 1e30, 1e30)"]),
            label="scale",
        ),
        "camera": data.draw(st.sampled_from(["(0, 0, 5)", "(0, 0, 0)", "(nan, 0, 5)", "(0, 0, 1e30)"]), label="camera"),
        "focal": _odd(data, "focal", "50"),
        "kind": data.draw(st.sampled_from(_KINDS), label="light kind"),
        "intensity": _odd(data, "intensity", "10"),
        "radius": _odd(data, "radius", "0.5"),
        "light": data.draw(st.sampled_from(["(0, 0, 3)", "(0, 0, 0)", "(inf, 0, 3)"]), label="light position"),
    }
    path = directory / "shot.usda"
    path.write_text(SHOT.format(**fields))
    return path


@pytest.mark.slow
@given(data=st.data())
def test_bad_shot_is_one_line_or_a_finite_bake(tmp_path, data):
    directory = Path(tempfile.mkdtemp(dir=tmp_path))
    try:
        shot = _shot(data, directory)
        out = directory / "out"
        with bounded(RENDER_SECONDS):
            status, stderr = quiet_main(
                [
                    "bake",
                    str(shot),
                    "--camera",
                    "/World/Camera",
                    "--out",
                    str(out),
                    "--width",
                    "8",
                    "--height",
                    "6",
                    "--supersampling",
                    "1",
                    "--texture-samples",
                    "1",
                ]
            )
        errors = [line for line in stderr.splitlines() if line.startswith("relight: error: ")]
        if status == 0:
            channels, _ = read_exr(out / "shot.dfb.exr")
            assert all(np.isfinite(values).all() for values in channels.values())
            assert_refused_or_finite(render(out / "shot.relight.usda", directory / "relit.exr"), out, shot)
        else:
            assert status == 2 and len(errors) == 1, stderr
            assert str(shot) in errors[0] or str(directory) in errors[0], errors[0]
            assert not list(out.glob("*.relight.usda"))
        tally("bad shot", method="direct", refused=status != 0)
    finally:
        shutil.rmtree(directory)


def test_lights_layer_sublayer_cycle_is_one_line(baked, tmp_path):
    layer = tmp_path / "lights.usda"
    layer.write_text("#usda 1.0\n(\n    subLayers = [@./lights.usda@]\n)\n")
    outcome = render(baked["direct"], tmp_path / "out" / "relit.exr", "--lights", str(layer))
    assert_refused_or_finite(outcome, layer, tmp_path)


@pytest.mark.parametrize(
    "declaration",
    [
        "int inputs:color = 0",
        'string inputs:color = "x"',
        "float3 inputs:width = (1, 2, 3)",
        'string inputs:normalize = "yes"',
        # pxr's Tf.ErrorException (a traceback naming no prim) from the light's world transform.
        'string xformOp:translate = "x"',
    ],
)
def test_a_light_input_authored_with_another_type_is_one_line(baked, tmp_path, declaration):
    # An int colour raised TypeError and a one-number colour IndexError in the light reader; a string
    # colour gave "could not convert string to float: 'x'" naming nothing.
    layer = tmp_path / "lights.usda"
    layer.write_text(
        '#usda 1.0\nover "World"\n{\n    over "Lights"\n    {\n        over "CeilingLight"\n'
        f"        {{\n            {declaration}\n        }}\n    }}\n}}\n"
    )
    outcome = render(baked["direct"], tmp_path / "out" / "relit.exr", "--lights", str(layer))
    name = declaration.split()[1]
    assert outcome.status == 2 and f"{LIGHT}: {name} = " in outcome.error and "authored as" in outcome.error, outcome
    assert str(layer) in outcome.error, outcome.error


def _write_shot(path: Path, **changes: str) -> Path:
    """SHOT (a wall, a camera, a sphere light) with `changes` to its fields, written to `path`."""
    fields = {
        "meters": "1",
        "counts": "[4]",
        "indices": "[0, 1, 2, 3]",
        "points": WALL,
        "scale": "(1, 1, 1)",
        "camera": "(0, 0, 5)",
        "focal": "50",
        "kind": "SphereLight",
        "intensity": "10",
        "radius": "0.5",
        "light": "(0, 0, 3)",
        **changes,
    }
    path.write_text(SHOT.format(**fields))
    return path


def _bake(shot: Path, out: Path, *options: str) -> tuple[int, str, list[str]]:
    """`relight bake` of `shot` at 8 x 6: (status, stderr, its error lines)."""
    arguments = ["--width", "8", "--height", "6", "--supersampling", "1", "--texture-samples", "1", *options]
    status, stderr = quiet_main(["bake", str(shot), "--camera", "/World/Camera", "--out", str(out), *arguments])
    return status, stderr, [line for line in stderr.splitlines() if line.startswith("relight: error: ")]


def test_a_mesh_of_empty_faces_is_an_empty_mesh(tmp_path):
    # faceVertexCounts = [0] and no indices ended the bake in numpy's "zero-size array to reduction".
    shot = _write_shot(tmp_path / "shot.usda", counts="[0]", indices="[]")
    status, stderr, errors = _bake(shot, tmp_path / "out")
    assert status == 2 and errors == [f"relight: error: stage {shot} has no renderable meshes or gprims"], stderr


def test_a_mesh_of_zero_scale_is_skipped_with_a_warning(tmp_path):
    # The subdivision dicing inverted its transform: numpy's LinAlgError ended the bake.
    shot = _write_shot(tmp_path / "shot.usda", scale="(0, 0, 0)")
    status, stderr, errors = _bake(shot, tmp_path / "out")
    warning = "/World/Wall: world transform of 1 of 1 placements is not finite and invertible (a zero scale?); skipped"
    assert status == 2 and len(errors) == 1 and warning in errors[0], stderr
    assert errors[0].startswith(f"relight: error: stage {shot} has no renderable meshes"), stderr


def test_an_xform_op_of_another_type_is_one_line(tmp_path):
    # pxr's Tf.ErrorException ended the bake in a traceback naming no prim (the mesh's, the camera's op).
    text = _write_shot(tmp_path / "shot.usda").read_text()
    shot = tmp_path / "mesh.usda"
    shot.write_text(text.replace("double3 xformOp:scale = (1, 1, 1)", 'string xformOp:scale = "x"'))
    status, stderr, errors = _bake(shot, tmp_path / "mesh", "--method", "direct")
    assert status == 2 and len(errors) == 1, stderr
    assert "/World/Wall: xformOp:scale = 'x' (authored as string) is not a transform; skipped" in stderr, stderr
    shot = tmp_path / "camera.usda"
    shot.write_text(text.replace("double3 xformOp:translate = (0, 0, 5)", 'string xformOp:translate = "x"'))
    status, stderr, errors = _bake(shot, tmp_path / "camera", "--method", "direct")
    assert status == 2 and errors == [
        f"relight: error: {shot}: camera /World/Camera: xformOp:translate = 'x' (authored as string) is not a transform"
    ], stderr


@pytest.mark.slow
def test_a_shot_no_quality_reaches_names_the_shot(tmp_path, monkeypatch):
    # The camera on the wall's plane: the --quality refusal named no file. The default (shot) bake
    # keeps its best effort and says so in one warning naming the shot. One small rung per ladder
    # keeps the test short (no size of this shot reaches the target).
    rung = {"gathers": 256, "coefficients": (10,), "bounceCoefficients": 256}
    monkeypatch.setattr(transfer_method, "METHOD", dataclasses.replace(transfer_method.METHOD, ladder=(rung,)))
    monkeypatch.setattr(shot_module, "TRANSFER_LADDER", [{**rung, "supersampling": 1}])
    shot = _write_shot(tmp_path / "shot.usda", camera="(0, 0, 0)")
    status, stderr, errors = _bake(shot, tmp_path / "sized", "--method", "transfer", "--quality", "35")
    assert status == 2 and len(errors) == 1 and str(shot) in errors[0], stderr
    status, stderr, errors = _bake(shot, tmp_path / "shot")
    warnings = [line for line in stderr.splitlines() if "not reached" in line]
    assert status == 0 and errors == [] and len(warnings) == 1 and str(shot) in warnings[0], stderr
