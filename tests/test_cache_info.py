"""`relight info CACHE`: provenance, method, parameters, payload sizes and the verdict; stages unchanged."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from cache_support import bake_bundled, copy_bake
from pipeline import cli
from relight_torch.cache.layer import read_cache_layer
from relight_torch.cache.status import cache_status


@pytest.fixture(scope="module")
def baked(tmp_path_factory) -> Path:
    return bake_bundled("glossy", tmp_path_factory.mktemp("baked"), supersampling=2)


@pytest.fixture
def cache(baked, tmp_path) -> Path:
    return copy_bake(baked, tmp_path)


def _info(path: Path, capsys, *options: str) -> tuple[int, str]:
    status = cli.main(["info", str(path), *options])
    return status, capsys.readouterr().out


def test_valid_cache_is_described_with_provenance_and_sizes(baked, capsys):
    status, out = _info(baked, capsys)
    assert status == 0
    description = read_cache_layer(baked)
    assert "  method: direct" in out and f"  source: {description.source}" in out
    assert "  camera: /World/Camera, 32x32, supersampling 2, exposure scale 1" in out
    assert f"  content hash: {description.content_hash}" in out
    assert "  parameters: supersampling = 2, textureSamples = 1" in out
    assert f"  inputs: {len(description.inputs)}" in out and "glossy_brick_albedo.png  unchanged" in out
    for payload in description.payloads:
        size = (baked.parent / payload.file).stat().st_size
        assert payload.num_bytes == size
        line = next(line for line in out.splitlines() if line.startswith(f"    {payload.name}: "))
        assert f"({size} bytes recorded)" in line and line.endswith(", ok")
    assert "      64x64, " in out and ", zip compression, " in out  # 32x32 pixels, 2x2 sub-samples each
    types = {kind: names.split() for kind, names in re.findall(r"^      (FLOAT|HALF|UINT): (.*)$", out, re.M)}
    assert sorted(types["FLOAT"]) == ["P.X", "P.Y", "P.Z", "Z"]
    assert types["UINT"] == ["materialId", "objectId"] and "N.X" in types["HALF"]
    assert "constant (not stored): clearcoat = 0" in out
    materials = re.search(r"^  materials: (\d+) \(edited by these prim paths\)\n((?:    .*\n)+)", out, re.M)
    assert materials is not None and "    /World/Materials/" in materials.group(2)
    assert int(materials.group(1)) == len(materials.group(2).splitlines())
    assert out.rstrip().endswith("  status: valid")


def test_stale_cache_names_the_changed_input(cache, capsys):
    texture = next(Path(f) for f in read_cache_layer(cache).inputs if f.endswith("glossy_brick_albedo.png"))
    texture.write_bytes(texture.read_bytes() + b"\0")
    status, out = _info(cache, capsys)
    assert status == 1
    assert f"    {texture}  changed" in out
    assert out.rstrip().endswith(f"  status: stale\n    input {texture} changed since the bake")
    assert cache_status(cache).verdict == "stale"


def test_corrupt_cache_names_the_bad_payload(cache, capsys):
    npy = cache.parent / "glossy.occluders.npy"
    npy.write_bytes(npy.read_bytes()[:1000])
    status, out = _info(cache, capsys)
    assert status == 1
    line = r"^    occluders: glossy.occluders.npy, npy, 1000 B \(\d+ bytes recorded\), float32\[\d+, 3, 3\], BAD$"
    assert re.search(line, out, re.M)
    assert "  status: corrupt" in out and f"{npy.resolve()}: payload occluders is truncated (1000 of" in out
    assert cache_status(cache).verdict == "corrupt"


def test_missing_payload_is_reported_not_raised(cache, capsys):
    (cache.parent / "glossy.dfb.exr").unlink()
    status, out = _info(cache, capsys)
    assert status == 1 and re.search(r"^    deepFramebuffer: glossy.dfb.exr, exr, missing ", out, re.M)
    assert "payload deepFramebuffer file" in out and "is missing" in out


def test_stage_options_are_refused_for_a_cache(baked, capsys):
    assert cli.main(["info", str(baked), "--camera", "/World/Camera"]) == 2
    assert "is a cache layer: stage options (--camera) do not apply" in capsys.readouterr().err


def test_stages_are_still_described(baked, capsys):
    status, out = _info(baked.parent.parent / "scene" / "glossy.usda", capsys)
    assert status == 0
    assert re.search(r"^  triangles: \d+$", out, re.M) and "  cameras: 1" in out
