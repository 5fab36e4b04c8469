"""The deep framebuffer EXR as other tools see it: OpenImageIO reads back exactly what we wrote,
only the channels the scene's materials vary are stored, each at the precision it needs."""

from __future__ import annotations

import dataclasses

import numpy as np
import OpenEXR
import OpenImageIO as oiio
import pytest

import pipeline.bake.direct.bake
from cache_support import SIZE, bake_bundled
from relight_torch.cache.gbuffer_exr import gbuffer_from_channels, gbuffer_to_channels
from relight_torch.cache.layer import read_cache_layer
from relight_torch.cache.load import load_gbuffer
from relight_torch.io.exr import read_exr, write_exr

SPECULAR = {"specularColor.R", "specularColor.G", "specularColor.B", "metallic", "clearcoat"}


def _bake_and_capture(name: str, directory, monkeypatch) -> tuple:
    """Bake `name`, keeping a copy of the channels handed to the EXR writer."""
    written = {}

    def spy(path, channels, attributes=None):
        written.update({n: a.copy() for n, a in channels.items()})
        write_exr(path, channels, attributes)

    monkeypatch.setattr(pipeline.bake.direct.bake, "write_exr", spy)
    layer = bake_bundled(name, directory)
    return layer, written


@pytest.fixture(scope="module")
def cornell(tmp_path_factory):
    with pytest.MonkeyPatch.context() as monkeypatch:
        return _bake_and_capture("cornell_box", tmp_path_factory.mktemp("cornell"), monkeypatch)


@pytest.fixture(scope="module")
def glossy(tmp_path_factory):
    with pytest.MonkeyPatch.context() as monkeypatch:
        return _bake_and_capture("glossy", tmp_path_factory.mktemp("glossy"), monkeypatch)


def _read_with_oiio(path) -> dict[str, np.ndarray]:
    """Every channel in its native type, as OpenImageIO (a client independent of OpenEXR's Python API) reads it."""
    image = oiio.ImageInput.open(str(path))
    assert image is not None, oiio.geterror()
    spec = image.spec()
    assert image.format_name() == "openexr" and spec.getattribute("compression") == "zip"
    channels = {}
    for index, name in enumerate(spec.channelnames):
        pixels = image.read_image(0, 0, index, index + 1, spec.channelformat(index))
        channels[name] = pixels[..., 0]
    image.close()
    return channels


@pytest.mark.parametrize("bake", ["cornell", "glossy"])
def test_openimageio_reads_back_what_we_wrote(bake, request):
    layer, written = request.getfixturevalue(bake)
    read = _read_with_oiio(layer.parent / f"{layer.name.split('.')[0]}.dfb.exr")
    assert set(read) == set(written)
    for name, array in written.items():
        assert read[name].dtype == array.dtype, name
        np.testing.assert_array_equal(read[name], array, err_msg=name)
    assert read["P.X"].dtype == np.float32 and read["N.X"].dtype == np.float16
    assert read["materialId"].dtype == np.uint32 and read["diffuseColor.R"].dtype == np.float16


def test_only_the_channels_the_materials_vary_are_stored(cornell, glossy):
    cornell_channels, glossy_channels = set(cornell[1]), set(glossy[1])
    # The Cornell box is matte: no specular colour, metal or clearcoat varies over it, so none is stored.
    assert not cornell_channels & SPECULAR
    assert {"specularColor.R", "specularColor.G", "specularColor.B", "metallic"} <= glossy_channels
    for layer, channels in (cornell, glossy):
        deep = read_cache_layer(layer).payload("deepFramebuffer")
        assert set(deep.channels) == set(channels)
        assert not set(deep.constants) & set(channels)
        assert deep.constants["emissiveColor.R"] == 0.0 and deep.constants["ior"] == 1.5
    cornell_deep = read_cache_layer(cornell[0]).payload("deepFramebuffer")
    assert cornell_deep.constants["specularColor.R"] == 0.0 and cornell_deep.constants["metallic"] == 0.0


def test_pixel_types_in_the_file(glossy):
    layer, _ = glossy
    with OpenEXR.File(str(layer.parent / "glossy.dfb.exr"), separate_channels=True) as exr:
        header = dict(exr.parts[0].header)  # the live header is cleared on close
        types = {name: channel.pixels.dtype for name, channel in exr.parts[0].channels.items()}
    assert header["compression"] == OpenEXR.ZIP_COMPRESSION
    for name in ("P.X", "P.Y", "P.Z", "Z"):
        assert types[name] == np.float32, name
    for name in ("materialId", "objectId"):
        assert types[name] == np.uint32, name
    assert {types[name] for name in types if name not in ("P.X", "P.Y", "P.Z", "Z", "materialId", "objectId")} == {
        np.dtype(np.float16)
    }


def test_loaded_gbuffer_matches_the_written_channels(glossy):
    layer, written = glossy
    gbuffer = load_gbuffer(layer, read_cache_layer(layer))
    covered = written["coverage"].reshape(-1) > 0.5
    assert gbuffer.num_samples == int(covered.sum()) and gbuffer.image_size == (SIZE, SIZE)
    np.testing.assert_array_equal(gbuffer.position[:, 1].numpy(), written["P.Y"].reshape(-1)[covered])
    np.testing.assert_array_equal(
        gbuffer.params.metallic.numpy(), written["metallic"].reshape(-1)[covered].astype(np.float32)
    )
    np.testing.assert_array_equal(gbuffer.material_id.numpy(), written["materialId"].reshape(-1)[covered])


def test_values_beyond_half_range_are_stored_as_float(glossy, tmp_path):
    layer, _ = glossy
    gbuffer = load_gbuffer(layer, read_cache_layer(layer))
    # A bright emitter: 1e5 nits overflows HALF (max 65504), so the channel must be FLOAT and exact.
    emissive = np.zeros((gbuffer.num_samples, 3), np.float32)
    emissive[::7, 0] = 1.0e5
    emissive[1::7, 0] = 0.5
    params = dataclasses.replace(gbuffer.params, emissive_color=gbuffer.params.emissive_color.new_tensor(emissive))
    channels, constants = gbuffer_to_channels(dataclasses.replace(gbuffer, params=params))
    assert channels["emissiveColor.R"].dtype == np.float32
    assert "emissiveColor.G" in constants and channels["diffuseColor.R"].dtype == np.float16
    write_exr(tmp_path / "bright.exr", channels)
    read, _ = read_exr(tmp_path / "bright.exr")
    rebuilt = gbuffer_from_channels(read, constants, gbuffer.camera_position.numpy(), "bright.exr")
    np.testing.assert_array_equal(rebuilt.params.emissive_color.numpy(), emissive)
