"""Bad caches and bad light layers are refused with one clear line naming the file, before any work.

Each case damages a private copy of a small bake the way it happens in a studio (a payload lost,
cut short by a full disk, overwritten by another bake, edited; the shot edited after the bake)
and checks the message says what is wrong. `relight render` turns each into exit status 2 with
`relight: error: ...` on stderr and writes nothing.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf

from cache_support import SIZE, bake_bundled, copy_bake
from pipeline import cli
from pipeline.errors import RelightError
from pipeline.scene import load_scene
from relight_torch.cache.layer import CACHE_VERSION, file_sha256
from relight_torch.direct.relighter import open_relighter
from relight_torch.io.exr import read_exr, write_exr


@pytest.fixture(scope="module")
def baked(tmp_path_factory) -> Path:
    return bake_bundled("cornell_box", tmp_path_factory.mktemp("baked"))


@pytest.fixture
def cache(baked, tmp_path) -> Path:
    return copy_bake(baked, tmp_path)


def _dfb(cache: Path) -> Path:
    return cache.parent / "cornell_box.dfb.exr"


def _occluders(cache: Path) -> Path:
    return cache.parent / "cornell_box.occluders.npy"


def _shot(cache: Path) -> Path:
    return cache.parent.parent / "scene" / "cornell_box.usda"


def _rerecord(cache: Path, payload: str, file: Path) -> None:
    """Make the layer record `file`'s current size and sha256, so only the header checks can object."""
    layer = Sdf.Layer.FindOrOpen(str(cache))
    prim = layer.GetPrimAtPath(f"/Cache/{payload}")
    prim.attributes["relight:sha256"].default = file_sha256(file)
    prim.attributes["relight:bytes"].default = file.stat().st_size
    layer.Save()


def _rewrite_dfb(cache: Path, change) -> None:
    """Rewrite the deep framebuffer with `change(channels)` applied, and record its new size and hash."""
    channels, _ = read_exr(_dfb(cache))
    change(channels)
    write_exr(_dfb(cache), channels)
    _rerecord(cache, "deepFramebuffer", _dfb(cache))


def _truncate(path: Path, num_bytes: int) -> None:
    path.write_bytes(path.read_bytes()[:num_bytes])


def _other_resolution(channels: dict) -> None:
    for name in channels:
        channels[name] = np.ascontiguousarray(channels[name][: SIZE // 2, : SIZE // 2])


def _three_nan_positions(channels: dict) -> None:
    """NaN in three pixels at the image centre (the box's back wall: covered)."""
    channels["P.Z"][SIZE // 2, SIZE // 2 - 1 : SIZE // 2 + 2] = np.nan


# (damage(cache), pattern the message must match; {dfb}/{occluders}/{shot} stand for the file paths)
CASES = {
    "payload missing": (lambda c: _dfb(c).unlink(), r"payload deepFramebuffer file {dfb} is missing"),
    "payload truncated": (
        lambda c: _truncate(_dfb(c), 5000),
        r"{dfb}: payload deepFramebuffer is truncated \(5000 of \d+ bytes\)",
    ),
    "header truncated": (
        lambda c: _truncate(_dfb(c), 100),
        r"{dfb}: payload deepFramebuffer is truncated \(100 of \d+ bytes\)",
    ),
    "payload edited in place": (
        lambda c: _dfb(c).write_bytes(_dfb(c).read_bytes()[:-1] + b"\x7f"),
        r"{dfb}: payload deepFramebuffer does not match the sha256 the cache layer records",
    ),
    "payload replaced by another resolution": (
        lambda c: write_exr(_dfb(c), {n: a[:16, :16].copy() for n, a in read_exr(_dfb(c))[0].items()}),
        r"{dfb}: payload deepFramebuffer is a 16x16 EXR, the cache layer says 32x32",
    ),
    "other resolution, layer re-recorded": (
        lambda c: _rewrite_dfb(c, _other_resolution),
        r"{dfb}: payload deepFramebuffer is a 16x16 EXR, the cache layer says 32x32",
    ),
    "channel dropped, layer re-recorded": (
        lambda c: _rewrite_dfb(c, lambda ch: ch.pop("N.Y")),
        r"{dfb}: payload deepFramebuffer channels differ from the cache layer's "
        r"\(unexpected \[\], missing \['N.Y'\]\)",
    ),
    "position stored as half, layer re-recorded": (
        lambda c: _rewrite_dfb(c, lambda ch: ch.update({"P.X": ch["P.X"].astype(np.float16)})),
        r"{dfb}: channel P.X is HALF, expected FLOAT",
    ),
    "non-finite positions, layer re-recorded": (
        lambda c: _rewrite_dfb(c, _three_nan_positions),
        r"{dfb}: channel P.Z has 3 non-finite covered values",
    ),
    "npy header garbage": (
        lambda c: _occluders(c).write_bytes(b"\x93NUMPY\x01\x00\x10\x00{'descr': oops}\n" + b"\0" * 1200),
        r"{occluders}: not a .npy array",
    ),
    "npy not numpy at all": (lambda c: _occluders(c).write_bytes(b"P3\n" * 500), r"{occluders}: not a .npy array"),
    "npy of another shape": (
        lambda c: np.save(_occluders(c), np.zeros((10, 3), np.float64)),
        r"{occluders}: payload occluders is float64\[10, 3\], the cache layer says float32\[\d+, 3, 3\]",
    ),
    "shot edited after the bake": (
        lambda c: _shot(c).write_text(_shot(c).read_text() + "\n# edited\n"),
        r"stale cache: input {shot} changed since the bake; re-bake it",
    ),
    "shot deleted": (lambda c: _shot(c).unlink(), r"stale cache: input {shot} missing since the bake"),
}


def _expected(pattern: str, cache: Path) -> str:
    paths = {"dfb": _dfb(cache), "occluders": _occluders(cache), "shot": _shot(cache)}
    return pattern.format(**{name: re.escape(str(path.resolve())) for name, path in paths.items()})


@pytest.mark.parametrize("case", CASES)
def test_damaged_cache_is_refused_saying_what_is_wrong(cache, case):
    damage, pattern = CASES[case]
    damage(cache)
    with pytest.raises(RelightError, match=_expected(pattern, cache)) as error:
        open_relighter(cache)
    assert "\n" not in str(error.value)


@pytest.mark.parametrize(
    "case",
    ["payload missing", "other resolution, layer re-recorded", "npy of another shape", "shot edited after the bake"],
)
def test_render_command_exits_2_with_one_line_and_writes_nothing(cache, case, capsys, tmp_path):
    damage, pattern = CASES[case]
    damage(cache)
    out = tmp_path / "out" / "relit.exr"
    assert cli.main(["render", str(cache), "-o", str(out), "--png", str(tmp_path / "relit.png")]) == 2
    stderr = capsys.readouterr().err
    assert stderr.startswith("relight: error: ") and stderr.count("\n") == 1
    assert re.search(_expected(pattern, cache), stderr)
    assert not out.exists() and not (tmp_path / "relit.png").exists()


def test_render_command_refuses_a_hand_edited_layer(cache, capsys, tmp_path):
    text = cache.read_text().replace(
        f"uniform int relight:version = {CACHE_VERSION}", "uniform int relight:version = 7"
    )
    cache.write_text(text)
    assert cli.main(["render", str(cache), "-o", str(tmp_path / "relit.exr")]) == 2
    assert capsys.readouterr().err == (
        f"relight: error: {cache}: cache version 7 is not supported "
        f"(this relight reads version {CACHE_VERSION}); re-bake it\n"
    )
    assert not (tmp_path / "relit.exr").exists()


def _lights_layer(directory: Path, body: str) -> Path:
    path = directory / "lights.usda"
    path.write_text(f'#usda 1.0\n(\n    defaultPrim = "Rig"\n)\n\ndef Xform "Rig"\n{{\n{body}\n}}\n')
    return path


def test_unknown_light_type_is_skipped_with_a_warning(cache, tmp_path, caplog, capsys):
    lights = _lights_layer(tmp_path, '    def PortalLight "Window"\n    {\n    }')
    warning = "/Rig/Window: light type 'PortalLight' is not supported; skipped"
    with caplog.at_level(logging.WARNING, logger="relight"):
        relighter = open_relighter(cache, lights_layer=lights)
    assert warning in caplog.messages
    shot_lights = {light.path for light in open_relighter(cache).lights}
    assert {light.path for light in relighter.lights} == shot_lights and shot_lights
    # `relight info SHOT --lights LAYER` lists it among the walker's warnings.
    assert cli.main(["info", str(_shot(cache)), "--lights", str(lights)]) == 0
    assert f"  warnings: 1\n    {warning}" in capsys.readouterr().out


def test_non_finite_light_attribute_names_prim_and_attribute_when_baking(cache, tmp_path):
    lights = _lights_layer(tmp_path, '    def SphereLight "Key"\n    {\n        float inputs:intensity = nan\n    }')
    with pytest.raises(RelightError, match=r"lights\.usda: /Rig/Key: inputs:intensity = nan must be finite"):
        load_scene(_shot(cache), lights_layer=lights, width=SIZE, height=SIZE)


def test_non_finite_light_attribute_names_prim_and_attribute_when_relighting(cache, tmp_path):
    lights = _lights_layer(tmp_path, '    def SphereLight "Key"\n    {\n        float inputs:intensity = nan\n    }')
    with pytest.raises(RelightError, match=r"/Rig/Key: inputs:intensity = nan must be finite"):
        open_relighter(cache, lights_layer=lights)
