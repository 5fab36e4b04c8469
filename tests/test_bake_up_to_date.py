"""A re-run of `relight bake` with the same request on unchanged inputs and code bakes nothing;
any change to the request, an input file or a payload bakes again."""

from __future__ import annotations

import pytest

from pipeline import cli
from pipeline.scenes import SCENES
from relight_torch.cache.layer import content_hash, read_cache_layer

SIZE = ["--width", "8", "--height", "8", "--texture-samples", "1"]


@pytest.fixture
def shot(tmp_path):
    return SCENES["cornell_box"].write(tmp_path / "scene")


def _bake(shot, out, capsys, *options) -> str:
    assert (
        cli.main(
            [
                "bake",
                str(shot),
                "--camera",
                SCENES["cornell_box"].camera,
                "--out",
                str(out),
                *SIZE,
                "--method",
                "direct",
                *options,
            ]
        )
        == 0
    )
    return capsys.readouterr().out


def test_same_request_is_up_to_date(shot, tmp_path, capsys):
    out = tmp_path / "cache"
    assert "up to date" not in _bake(shot, out, capsys, "--supersampling", "1")
    layer = out / "cornell_box.relight.usda"
    written = layer.stat().st_mtime_ns
    assert "up to date" in _bake(shot, out, capsys, "--supersampling", "1", "--workers", "1")
    assert layer.stat().st_mtime_ns == written
    description = read_cache_layer(layer)
    assert "request" in description.parameters
    # The recorded content hash still covers every recorded parameter, the request included.
    assert description.content_hash == content_hash(
        description.inputs, description.parameters, description.code_version
    )


@pytest.mark.parametrize("change", ["option", "input", "payload"])
def test_a_change_bakes_again(shot, tmp_path, capsys, change):
    out = tmp_path / "cache"
    _bake(shot, out, capsys, "--supersampling", "1")
    options = ["--supersampling", "2" if change == "option" else "1"]
    if change == "input":
        shot.write_text(shot.read_text() + "\n")
    if change == "payload":
        payload = out / "cornell_box.occluders.npy"
        data = bytearray(payload.read_bytes())
        data[-1] ^= 1
        payload.write_bytes(bytes(data))
    assert "up to date" not in _bake(shot, out, capsys, *options)
    assert read_cache_layer(out / "cornell_box.relight.usda").supersampling == int(options[1])
