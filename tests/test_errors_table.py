"""Bad input, end to end: each row of docs/ERRORS.md is one test here.

Each runs the `relight` command as a user would, on a tiny shot written for the case, and checks
the message (one line naming the file and the prim), the exit status (2 where fatal, 0 with a
warning where the bake can go on) and that nothing partial is left behind.
"""

from __future__ import annotations

import errno
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.cli import main
from relight_torch.cache.layer import SUFFIX, read_cache_layer, write_cache_layer
from relight_torch.cache.status import cache_status
from relight_torch.io.exr import read_exr

WALL = "[(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)]"
SHOT = """#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1{metadata}
)
def Xform "World"
{{
    def Mesh "Wall"
    {{
        int[] faceVertexCounts = {counts}
        int[] faceVertexIndices = {indices}
        point3f[] points = {points}{wall}
    }}
    def Camera "Camera"
    {{
        double3 xformOp:translate = {camera}
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }}
    def SphereLight "Key"
    {{
        float inputs:intensity = {intensity}
        double3 xformOp:translate = (0, 0, 3)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }}{extra}
}}
"""
TEXTURED = """
        texCoord2f[] primvars:st = [(0, 0), (1, 0), (1, 1), (0, 1)] (interpolation = "vertex")
        rel material:binding = </World/Paint>"""
PAINT = """
    def Material "Paint"
    {
        token outputs:surface.connect = </World/Paint/Surface.outputs:surface>
        def Shader "Surface"
        {
            uniform token info:id = "UsdPreviewSurface"
            color3f inputs:diffuseColor.connect = </World/Paint/Texture.outputs:rgb>
            token outputs:surface
        }
        def Shader "Texture"
        {
            uniform token info:id = "UsdUVTexture"
            asset inputs:file = @./notes.png@
            float3 outputs:rgb
        }
    }"""


def _shot(directory: Path, **changes: str) -> Path:
    """Write the tiny shot (a wall facing a camera, a sphere light) with `changes` to its template."""
    fields = {
        "metadata": "",
        "counts": "[4]",
        "indices": "[0, 1, 2, 3]",
        "points": WALL,
        "wall": "",
        "camera": "(0, 0, 5)",
        "intensity": "10",
        "extra": "",
    }
    path = directory / "shot.usda"
    path.write_text(SHOT.format(**{**fields, **changes}))
    return path


@pytest.fixture
def bake(capsys, caplog):
    """`bake(shot, out)`: `relight bake` of `shot` at 8 x 8 into `out` -> (exit status, stderr), the
    warnings included (pytest's log capture takes them from the stderr handler)."""

    def run(shot: Path, out: Path) -> tuple[int, str]:
        caplog.clear()
        status = main(
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
                "8",
                "--supersampling",
                "1",
                "--texture-samples",
                "1",
                "--method",
                "direct",
            ]
        )
        warnings = [f"relight: WARNING: {r.getMessage()}" for r in caplog.records if r.levelname == "WARNING"]
        return status, "\n".join(warnings + [capsys.readouterr().err])

    return run


def _error_line(stderr: str) -> str:
    """The one `relight: error:` line, which must be the last line."""
    lines = [line for line in stderr.splitlines() if line.startswith("relight: ")]
    assert lines and lines[-1].startswith("relight: error: "), stderr
    return lines[-1]


def _assert_fatal(status: int, stderr: str, out: Path, *names: str) -> None:
    """Exit 2, one error line naming every one of `names`, and no output at all."""
    assert status == 2
    line = _error_line(stderr)
    assert all(name in line for name in names), line
    assert not out.exists() or not any(out.rglob("*")), sorted(out.rglob("*"))


def _assert_baked_with_warning(status: int, stderr: str, out: Path, *names: str) -> None:
    """Exit 0, a warning naming every one of `names`, and a valid cache whose pixels are finite."""
    assert status == 0, stderr
    warnings = [line for line in stderr.splitlines() if line.startswith("relight: WARNING: ")]
    assert any(all(name in w for name in names) for w in warnings), stderr
    layer = out / f"shot{SUFFIX}"
    assert cache_status(layer).verdict == "valid"
    channels, _ = read_exr(out / "shot.dfb.exr")
    assert all(np.isfinite(values).all() for values in channels.values())


def test_malformed_usd(tmp_path, bake):
    shot = tmp_path / "shot.usda"
    shot.write_text('#usda 1.0\ndef Xform "World"\n{\n    this is not usd\n')
    _assert_fatal(*bake(shot, tmp_path / "out"), tmp_path / "out", "shot.usda", "</World>")


def test_missing_sublayer(tmp_path, bake):
    shot = _shot(tmp_path, metadata="\n    subLayers = [@./set.usda@]")
    _assert_fatal(*bake(shot, tmp_path / "out"), tmp_path / "out", "shot.usda", "set.usda", "Could not load sublayer")


def test_out_of_range_indices(tmp_path, bake):
    shot = _shot(tmp_path, indices="[0, 1, 2, 9]")
    _assert_fatal(
        *bake(shot, tmp_path / "out"), tmp_path / "out", "shot.usda", "/World/Wall", "do not match its 4 points"
    )


def test_nan_and_huge_coordinates(tmp_path, bake):
    # Two good triangles, one with a NaN corner, one with a corner at 1e30 (its area overflows).
    shot = _shot(
        tmp_path,
        counts="[4, 3, 3]",
        indices="[0, 1, 2, 3, 0, 1, 4, 0, 1, 5]",
        points="[(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0), (nan, 0, 0), (1e30, 0, 0)]",
    )
    _assert_baked_with_warning(
        *bake(shot, tmp_path / "out"), tmp_path / "out", "/World/Wall", "dropped 2 degenerate or non-finite triangles"
    )


def test_zero_area_and_sliver_triangles(tmp_path, bake):
    # The wall, a zero-area triangle (a repeated corner) and a sliver 1e-7 wide, which is kept.
    shot = _shot(
        tmp_path,
        counts="[4, 3, 3]",
        indices="[0, 1, 2, 3, 0, 0, 1, 0, 1, 4]",
        points="[(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0), (0, -0.9999999, 1e-7)]",
    )
    _assert_baked_with_warning(
        *bake(shot, tmp_path / "out"), tmp_path / "out", "/World/Wall", "dropped 1 degenerate or non-finite triangles"
    )
    assert read_cache_layer(tmp_path / "out" / f"shot{SUFFIX}").payload("occluders").shape == (3, 3, 3)


def test_camera_inside_geometry(tmp_path, bake):
    shot = _shot(
        tmp_path,
        camera="(0, 0, 0)",
        points=WALL.replace(", 0)", ", 1.5)"),
        extra='\n    def Cube "Box"\n    {\n        double size = 4\n    }',
    )
    _assert_baked_with_warning(
        *bake(shot, tmp_path / "out"), tmp_path / "out", "shot.usda", "/World/Camera", "inside geometry"
    )


@pytest.mark.parametrize("intensity", ["-10", "nan"])
def test_negative_or_nan_light_intensity(tmp_path, bake, intensity):
    shot = _shot(tmp_path, intensity=intensity)
    _assert_fatal(
        *bake(shot, tmp_path / "out"),
        tmp_path / "out",
        "shot.usda",
        "/World/Key",
        "inputs:intensity",
        "must be finite and >= 0",
    )


def test_texture_that_is_not_an_image(tmp_path, bake):
    (tmp_path / "notes.png").write_text("a text file named like a picture\n")
    shot = _shot(tmp_path, wall=TEXTURED, extra=PAINT)
    _assert_baked_with_warning(
        *bake(shot, tmp_path / "out"), tmp_path / "out", "/World/Paint", "notes.png", "Not a PNG file"
    )


def test_disk_full_mid_write(tmp_path, bake, monkeypatch):
    shot = _shot(tmp_path)
    out = tmp_path / "out"
    real_fsync, calls = os.fsync, []

    def fills_up(descriptor):  # the atomic writer's flush: the third file finds the disk full
        calls.append(descriptor)
        if len(calls) == 3:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_fsync(descriptor)

    monkeypatch.setattr(os, "fsync", fills_up)
    status, stderr = bake(shot, out)
    assert status == 2
    line = _error_line(stderr)
    assert "No space left on device" in line and str(out) in line
    assert not list(out.rglob(".*.tmp-*")) and not list(out.glob(f"*{SUFFIX}"))  # no partial output
    monkeypatch.undo()
    assert bake(shot, out)[0] == 0 and cache_status(out / f"shot{SUFFIX}").verdict == "valid"


@pytest.fixture
def cache(tmp_path, bake) -> Path:
    """A valid tiny cache."""
    status, stderr = bake(_shot(tmp_path), tmp_path / "out")
    assert status == 0, stderr
    return tmp_path / "out" / f"shot{SUFFIX}"


def test_cache_edited_by_hand(cache, tmp_path, capsys):
    dfb = cache.parent / "shot.dfb.exr"
    data = bytearray(dfb.read_bytes())
    data[-9] ^= 0xFF  # one byte of pixel data
    dfb.write_bytes(bytes(data))
    assert main(["info", str(cache)]) == 1
    assert "status: corrupt" in capsys.readouterr().out
    image = tmp_path / "relit.exr"
    assert main(["render", str(cache), "-o", str(image)]) == 2
    line = _error_line(capsys.readouterr().err)
    assert str(dfb) in line and "deepFramebuffer" in line and "sha256" in line
    assert not image.exists()


def test_cache_header_claiming_a_huge_shape_is_refused_before_allocating(cache, tmp_path):
    # A consistent forgery: the .npy header and the layer's record both claim 10^12 triangles.
    occluders = cache.parent / "shot.occluders.npy"
    data = occluders.read_bytes()
    header_end = data.index(b"\n") + 1
    shape = "(1000000000000, 3, 3)"
    header = data[:header_end].decode("latin1")
    old_shape = header[header.index("'shape': ") + 9 : header.index("), ") + 1]
    forged = header.replace(old_shape, shape)
    forged = forged[:-1].rstrip(" ") + " " * (header_end - len(forged[:-1].rstrip(" ")) - 1) + "\n"
    assert len(forged) == header_end
    occluders.write_bytes(forged.encode("latin1") + data[header_end:])
    description = read_cache_layer(cache)
    payloads = tuple(
        p if p.name != "occluders" else type(p)(**{**vars(p), "shape": (10**12, 3, 3), "sha256": _sha256(occluders)})
        for p in description.payloads
    )
    write_cache_layer(cache, type(description)(**{**vars(description), "payloads": payloads}))
    # In a fresh process: a test worker's threads left by earlier tests would count in the trace too.
    script = (
        "import sys, tracemalloc\n"
        "from pipeline.cli import main\n"
        "tracemalloc.start()\n"
        "status = main(sys.argv[1:])\n"
        "print('peak', tracemalloc.get_traced_memory()[1])\n"
        "sys.exit(status)\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script, "render", str(cache), "-o", str(tmp_path / "relit.exr")],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])},
    )
    status, peak = result.returncode, int(result.stdout.split("peak")[-1])
    assert status == 2
    line = _error_line(result.stderr)
    assert str(occluders) in line and "refused before reading" in line
    assert peak < 64 * 2**20 < math.prod((10**12, 3, 3)) * 4  # nothing near the claimed 36 TB


def _sha256(path: Path) -> str:
    from relight_torch.cache.layer import file_sha256

    return file_sha256(path)
