"""Damaged caches of every method, generated: each `relight render` refuses with one line naming the
file, or (where the damage is harmless) renders finite pixels; never a traceback, a hang or NaN.

The damage is what disks, copies and hands do to a cache: bits flipped anywhere or in a header,
files cut short, swapped or lost, the layer's attributes edited to odd values, and .npy headers
forged (with the layer's record) to claim huge shapes. Bounded example counts by default;
HYPOTHESIS_PROFILE=nightly runs many more (tests/fuzz_support.py).
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pxr import Gf, Sdf, Vt

from fuzz_support import (
    METHODS,
    assert_refused_or_finite,
    bake_all,
    copy_cache,
    npy_header_span,
    payload_files,
    render,
    tally,
)
from relight_torch.cache.layer import file_sha256, read_cache_layer
from relight_torch.cache.load import load_npy
from relight_torch.errors import RelightError


@pytest.fixture(scope="module")
def baked(tmp_path_factory) -> dict[str, Path]:
    return bake_all(tmp_path_factory.mktemp("fuzz_bakes"))


def _rerecord(layer: Path, file: Path, **attributes) -> None:
    """Make the layer record `file`'s current size and sha256 (and `attributes`) for the payload naming it."""
    sdf = Sdf.Layer.FindOrOpen(str(layer))
    for prim in sdf.GetPrimAtPath("/Cache").nameChildren:
        if prim.attributes["relight:file"].default.path == f"./{file.name}":
            prim.attributes["relight:sha256"].default = file_sha256(file)
            prim.attributes["relight:bytes"].default = file.stat().st_size
            for name, value in attributes.items():
                prim.attributes[name].default = value
    sdf.Save()


def _flip_bits(data: st.DataObject, file: Path, in_header: bool) -> None:
    content = bytearray(file.read_bytes())
    end = min(len(content), npy_header_span(file) if file.suffix == ".npy" else 512) if in_header else len(content)
    for _ in range(data.draw(st.integers(1, 8), label="bits")):
        position = data.draw(st.integers(0, end - 1), label="byte")
        content[position] ^= 1 << data.draw(st.integers(0, 7), label="bit")
    file.write_bytes(bytes(content))


def _huge_shape(layer: Path, file: Path, factor: int) -> None:
    """Forge a .npy header (and the layer's record of it) claiming `factor` times its first axis over the same data."""
    content = file.read_bytes()
    header = content[10 : npy_header_span(file)].decode("latin1")  # after the magic, version and length
    old = header[header.index("'shape': (") + 10 : header.index(")", header.index("'shape': ("))]
    dims = [int(n) for n in old.split(",") if n.strip()] or [1]
    dims[0] = min(max(dims[0], 1) * factor, 2**62)
    text = header[: header.index("'shape': (") + 10] + ", ".join(map(str, dims)) + ("," if len(dims) == 1 else "")
    text += header[header.index(")", header.index("'shape': (")) :]
    text = text.rstrip("\n ")
    text += " " * ((64 - (10 + len(text) + 1) % 64) % 64) + "\n"
    file.write_bytes(
        b"\x93NUMPY\x01\x00"
        + len(text).to_bytes(2, "little")
        + text.encode("latin1")
        + content[npy_header_span(file) :]
    )
    _rerecord(layer, file, **{"relight:shape": Vt.Int64Array(dims)})


_ODD_INTS = [-(2**31), -1, 0, 1, 2, 3, 7, 2**20, 2**31 - 1]
_ODD_INT64S = _ODD_INTS + [2**40, 2**62]
_ODD_DOUBLES = [math.nan, math.inf, -math.inf, 0.0, -1.0, 1e-300, 1e300]
_ODD_STRINGS = ["", "x", "float64", "object", "npy", "exr", "O", "|V0", "<f4", "../x", "\u00e9\n"]
_ODD_ASSETS = [
    "",
    "./missing.npy",
    "../scene/cornell_box.usda",
    "/etc/hostname",
    "./",
    "../../x.npy",
    "./cornell_box.occluders.npy",
    "./cornell_box.dfb.exr",
]


def _odd_value(data: st.DataObject, type_name: str, current):
    """An odd value of the attribute's own type (the layer stays loadable by USD)."""
    draw = data.draw
    if type_name == "int":
        return draw(st.sampled_from(_ODD_INTS + [current + 1, current - 1]), label="int")
    if type_name == "int64":
        return draw(st.sampled_from(_ODD_INT64S + [current + 1, current - 1]), label="int64")
    if type_name == "double":
        return draw(st.sampled_from(_ODD_DOUBLES + [2 * current]), label="double")
    if type_name in ("string", "token"):
        return draw(st.sampled_from(_ODD_STRINGS), label="string")
    if type_name == "asset":
        return Sdf.AssetPath(draw(st.sampled_from(_ODD_ASSETS), label="asset"))
    if type_name == "int2":
        return Gf.Vec2i(
            *draw(st.sampled_from([(0, 12), (-16, 12), (16, 0), (32, 24), (8, 6), (2**30, 12)]), label="int2")
        )
    if type_name == "matrix4d":
        return draw(
            st.sampled_from(
                [Gf.Matrix4d(0.0), Gf.Matrix4d(math.nan), Gf.Matrix4d(1e300), Gf.Matrix4d(1.0), Gf.Matrix4d(-1.0)]
            ),
            label="matrix",
        )
    items = list(current)
    kind = draw(st.sampled_from(["empty", "drop", "double", "odd"]), label="array edit")
    if kind == "empty" or (kind == "drop" and not items):
        items = []
    elif kind == "drop":
        items = items[:-1]
    elif kind == "double":
        items = items + items
    else:
        odd = {"int64[]": _ODD_INT64S, "double[]": _ODD_DOUBLES, "string[]": _ODD_STRINGS}[type_name]
        index = draw(st.integers(0, max(len(items) - 1, 0)), label="index")
        items[index : index + 1] = [draw(st.sampled_from(odd), label="item")]
    return {"int64[]": Vt.Int64Array, "double[]": Vt.DoubleArray, "string[]": Vt.StringArray}[type_name](items)


def _edit_attribute(data: st.DataObject, layer: Path) -> None:
    """Set one authored attribute of the cache layer to an odd value, retype it, or remove it."""
    sdf = Sdf.Layer.FindOrOpen(str(layer))
    cache = sdf.GetPrimAtPath("/Cache")
    attributes = list(cache.attributes) + [a for child in cache.nameChildren for a in child.attributes]
    attribute = data.draw(st.sampled_from(sorted(attributes, key=lambda a: str(a.path))), label="attribute")
    action = data.draw(st.sampled_from(["value", "value", "value", "retype", "remove"]), label="action")
    owner = attribute.owner
    if action == "remove":
        owner.RemoveProperty(attribute)
    elif action == "retype":
        name, new_type = attribute.name, data.draw(st.sampled_from(["string", "double", "int", "bool"]), label="type")
        owner.RemoveProperty(attribute)
        spec = Sdf.AttributeSpec(owner, name, getattr(Sdf.ValueTypeNames, new_type.capitalize()))
        spec.default = {"string": "x", "double": 1.5, "int": 1, "bool": True}[new_type]
    else:
        attribute.default = _odd_value(data, str(attribute.typeName), attribute.default)
    sdf.Save()


def _damage(data: st.DataObject, layer: Path) -> str:
    """Apply one drawn kind of damage to the cache at `layer`; returns the kind."""
    files = payload_files(layer)
    kind = data.draw(
        st.sampled_from(
            ["flip", "flip header", "truncate", "swap", "missing", "edit layer", "huge shape", "flip layer"]
        ),
        label="kind",
    )
    file = data.draw(st.sampled_from(files), label="file")
    if kind in ("flip", "flip header"):
        _flip_bits(data, file, kind == "flip header")
    elif kind == "flip layer":
        _flip_bits(data, layer, False)
    elif kind == "truncate":
        file.write_bytes(file.read_bytes()[: data.draw(st.integers(0, file.stat().st_size - 1), label="length")])
    elif kind == "swap":
        other = data.draw(st.sampled_from([f for f in files if f != file] or [file]), label="other")
        temp = file.with_name("swap.tmp")
        file.rename(temp)
        other.rename(file)
        temp.rename(other)
    elif kind == "missing":
        file.unlink()
    elif kind == "edit layer":
        _edit_attribute(data, layer)
    else:
        npys = [f for f in files if f.suffix == ".npy"]
        file = data.draw(st.sampled_from(npys), label="npy")
        _huge_shape(layer, file, data.draw(st.sampled_from([10**3, 10**6, 10**12, 2**62]), label="factor"))
    return kind


@pytest.mark.slow
@pytest.mark.parametrize("method", METHODS)
@given(data=st.data())
def test_damaged_cache_is_refused_in_one_line_or_renders_finite_pixels(baked, tmp_path, method, data):
    directory = Path(tempfile.mkdtemp(dir=tmp_path))
    try:
        layer = copy_cache(baked[method], directory)
        kind = _damage(data, layer)
        outcome = render(layer, directory / "out" / "relit.exr")
        # Harmless damage (an attribute nothing reads) may render: finite pixels then, whatever they are
        # (an edited exposure legitimately changes them).
        assert_refused_or_finite(outcome, layer.parent, layer.parent.resolve())
        tally("damaged cache", method=method, damage=kind, refused=outcome.status != 0)
    finally:
        shutil.rmtree(directory)


def _flip_header_byte(file: Path, character: bytes) -> None:
    """Invert all eight bits of the first `character` in a .npy header."""
    content = bytearray(file.read_bytes())
    position = content.index(character, 0, npy_header_span(file))
    content[position] ^= 0xFF
    file.write_bytes(bytes(content))


def test_eight_flipped_bits_in_a_npy_header_are_one_line_naming_the_file(baked, tmp_path):
    # The closing brace of gatherArea.npy's header inverted: numpy's own header parser ended
    # `relight render` in a tokenize.TokenError traceback.
    layer = copy_cache(baked["transfer"], tmp_path)
    area = layer.parent / "cornell_box.gatherArea.npy"
    _flip_header_byte(area, b"}")
    outcome = render(layer, tmp_path / "out" / "relit.exr")
    assert outcome.status == 2 and f"{area.resolve()}: not a .npy array (malformed header" in outcome.error


@pytest.mark.parametrize(
    "header",
    [
        b"{'descr': '<f4', 'fortran_order': False, 'shape': (4,), ",  # unclosed (TokenError in numpy)
        b"{'descr': '<f4', 'fortran_order': False, 'shape': (4,), }" + b"(" * 200,  # nested too deep
        b"{'descr': 'O', 'fortran_order': False, 'shape': (4,), }",  # objects: needs pickle
        b"{'descr': '|V0', 'fortran_order': False, 'shape': (1000000000000,), }",  # zero-size items
        b"{'descr': '<f4', 'fortran_order': 1, 'shape': (4,), }",
        b"{'descr': '<f4', 'fortran_order': False, 'shape': (-4,), }",
        b"{'descr': '<f4', 'fortran_order': False, 'shape': (True,), }",
        b"{'descr': [('a', '<f4')], 'fortran_order': False, 'shape': (4,), }",
        b"{'descr': '<f4', 'shape': (4,), }",
        b"['descr', '<f4']",
        b"\xff\xfe{}",
    ],
)
def test_malformed_npy_headers_are_one_line_naming_the_file(tmp_path, header):
    from relight_torch.cache.load import read_npy_header

    path = tmp_path / "bad.npy"
    text = header + b" " * ((64 - (10 + len(header) + 1) % 64) % 64) + b"\n"
    path.write_bytes(b"\x93NUMPY\x01\x00" + len(text).to_bytes(2, "little") + text + b"\0" * 16)
    with pytest.raises(RelightError, match=f"^{path}: not a .npy array") as error:
        read_npy_header(path)
    assert "\n" not in str(error.value)


@pytest.mark.parametrize("header_length", [0, 10_001, 65_535])
def test_npy_header_lengths_outside_the_limit_are_refused(tmp_path, header_length):
    from relight_torch.cache.load import read_npy_header

    path = tmp_path / "bad.npy"
    path.write_bytes(b"\x93NUMPY\x01\x00" + header_length.to_bytes(2, "little") + b" " * 64)
    with pytest.raises(RelightError, match=f"^{path}: not a .npy array"):
        read_npy_header(path)


def test_a_huge_declared_shape_is_refused_before_allocating(baked, tmp_path):
    layer = copy_cache(baked["gather"], tmp_path)
    file = layer.parent / "cornell_box.gatherPosition.npy"
    _huge_shape(layer, file, 2**62)
    # In a fresh process: a test worker's threads left by earlier tests would count in the trace too.
    script = (
        "import sys, tracemalloc\n"
        "from relight_torch.cache.layer import read_cache_layer\n"
        "from relight_torch.cache.load import load_npy\n"
        "from relight_torch.errors import RelightError\n"
        "description = read_cache_layer(sys.argv[1])\n"
        "tracemalloc.start()\n"
        "try:\n"
        "    load_npy(sys.argv[1], description, 'gatherPosition')\n"
        "except RelightError as error:\n"
        "    print(error)\n"
        "print('peak', tracemalloc.get_traced_memory()[1])\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script, str(layer)],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])},
    )
    assert f"{file.resolve()}: .npy header claims float32" in result.stdout, result.stdout + result.stderr
    peak = int(result.stdout.split("peak")[-1])
    assert peak < 1 << 20


def test_an_exr_payload_loaded_as_npy_is_one_line(baked):
    """load_npy of the deep framebuffer used to unpack the EXR header as a .npy one (TypeError)."""
    description = read_cache_layer(baked["gather"])
    with pytest.raises(RelightError, match=r"payload deepFramebuffer is an EXR image, not a \.npy array"):
        load_npy(baked["gather"], description, "deepFramebuffer")


@pytest.mark.parametrize("file", ["../scene/cornell_box.usda", "/etc/hostname", "./sub/../../direct/x.npy", "..", "."])
def test_a_payload_path_out_of_the_cache_folder_is_refused(baked, tmp_path, file):
    layer = copy_cache(baked["direct"], tmp_path)
    sdf = Sdf.Layer.FindOrOpen(str(layer))
    sdf.GetPrimAtPath("/Cache/occluders").attributes["relight:file"].default = Sdf.AssetPath(file)
    sdf.Save()
    outcome = render(layer, tmp_path / "out" / "relit.exr")
    assert outcome.status == 2
    assert outcome.error == (
        f"relight: error: {layer}: /Cache/occluders.relight:file {file!r} is not a file in the cache layer's own folder"
    )


def test_a_cache_layer_with_bytes_that_are_not_utf8_is_one_line(baked, tmp_path):
    # pxr cannot build the text of its own parse error here: str() of it raised UnicodeDecodeError.
    layer = copy_cache(baked["direct"], tmp_path)
    content = bytearray(layer.read_bytes())
    content[5] ^= 0x80
    layer.write_bytes(bytes(content))
    outcome = render(layer, tmp_path / "out" / "relit.exr")
    assert outcome.status == 2
    assert outcome.error.startswith(f"relight: error: {layer}: not a readable USD layer")


def test_an_exr_header_damaged_into_bytes_that_are_not_utf8_is_one_line(baked, tmp_path):
    # OpenImageIO's error quotes the damaged attribute type name; its binding raised UnicodeDecodeError.
    layer = copy_cache(baked["direct"], tmp_path)
    dfb = layer.parent / "cornell_box.dfb.exr"
    content = bytearray(dfb.read_bytes())
    content[16] |= 0x80  # in 'chlist', the type name of the channels attribute
    dfb.write_bytes(bytes(content))
    outcome = render(layer, tmp_path / "out" / "relit.exr")
    assert outcome.status == 2
    assert outcome.error.startswith(f"relight: error: {dfb.resolve()}: ")


def test_a_transfer_layer_that_lost_its_row_colour_parameter_is_refused(baked, tmp_path):
    # The rows' scalar values were read as three channels: an IndexError deep in the relighter.
    layer = copy_cache(baked["transfer"], tmp_path)
    sdf = Sdf.Layer.FindOrOpen(str(layer))
    cache = sdf.GetPrimAtPath("/Cache")
    cache.RemoveProperty(cache.attributes["relight:parameters:rowColour"])
    sdf.Save()
    outcome = render(layer, tmp_path / "out" / "relit.exr")
    assert outcome.status == 2
    assert outcome.error.startswith(
        f"relight: error: {layer}: finalGather rows are malformed (values without a row colour must be (nnz, 3)"
    )
