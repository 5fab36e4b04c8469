"""Texture reading and sampling: hand-computed values on tiny images written with OpenImageIO."""

import numpy as np
import OpenImageIO as oiio
import pytest

from pipeline.errors import RelightError
from pipeline.scene.textures import (
    ImageCache,
    expand_to_rgba,
    fit_channels,
    load_texture,
    sample_texture,
    select_output,
)
from pipeline.scene.types import Texture
from relight_torch.io.images import read_image, srgb_to_linear


def write_image(path, pixels, type_name, attributes=()):
    """Write (H, W, C) pixels (row 0 = top) with OIIO; returns the path as str."""
    height, width, num_channels = pixels.shape
    spec = oiio.ImageSpec(width, height, num_channels, type_name)
    spec.attribute("oiio:UnassociatedAlpha", 1)  # write PNG alpha as given, not un-premultiplied
    for name, value in attributes:
        spec.attribute(name, value)
    output = oiio.ImageOutput.create(str(path))
    assert output.open(str(path), spec), oiio.geterror()
    assert output.write_image(pixels)
    output.close()
    return str(path)


def texture_of(pixels, wrap_s="repeat", wrap_t="repeat", **fields):
    return Texture(file="<memory>", pixels=np.asarray(pixels, np.float32), wrap_s=wrap_s, wrap_t=wrap_t, **fields)


# --- reading and colour decoding ----------------------------------------------------------------


def test_srgb_eotf_known_values():
    # 128/255 is above the 0.04045 knee: ((0.50196 + 0.055) / 1.055)^2.4 = 0.21586
    # 10/255 is below it: 0.039216 / 12.92 = 0.0030353
    encoded = np.array([128 / 255, 10 / 255, 0.0, 1.0], np.float32)
    np.testing.assert_allclose(srgb_to_linear(encoded), [0.215861, 0.00303527, 0.0, 1.0], rtol=1e-5)


def test_auto_decodes_8bit_rgb_but_not_alpha(tmp_path):
    pixels = np.array([[[128, 10, 255, 128]]], np.uint8)
    path = write_image(tmp_path / "a.png", pixels, "uint8")
    decoded = read_image(path, "auto").pixels
    np.testing.assert_allclose(decoded[0, 0], [0.215861, 0.00303527, 1.0, 128 / 255], rtol=1e-5)
    np.testing.assert_allclose(read_image(path, "raw").pixels[0, 0], pixels[0, 0] / 255, rtol=1e-6)


def test_auto_leaves_single_channel_raw_and_srgb_decodes_it(tmp_path):
    path = write_image(tmp_path / "grey.png", np.array([[[128]]], np.uint8), "uint8")
    np.testing.assert_allclose(read_image(path, "auto").pixels[0, 0], [128 / 255], rtol=1e-6)
    np.testing.assert_allclose(read_image(path, "sRGB").pixels[0, 0], [0.215861], rtol=1e-5)


@pytest.mark.parametrize("suffix", ["exr", "hdr"])
def test_float_images_are_raw_under_auto(tmp_path, suffix):
    # Powers of two survive RGBE (.hdr) exactly; values above 1 must not be clipped or decoded.
    pixels = np.array([[[2.0, 0.5, 4.0], [0.25, 1.0, 8.0]]], np.float32)
    path = write_image(tmp_path / f"f.{suffix}", pixels, "float")
    np.testing.assert_allclose(read_image(path, "auto").pixels, pixels, rtol=1e-6)


def test_jpeg_is_read_as_srgb(tmp_path):
    path = write_image(tmp_path / "flat.jpg", np.full((8, 8, 3), 128, np.uint8), "uint8")
    # JPEG is lossy, but a flat grey block comes back within a code value or two.
    np.testing.assert_allclose(read_image(path, "auto").pixels, 0.215861, atol=0.01)


def test_missing_and_corrupt_files_raise_naming_the_file(tmp_path):
    with pytest.raises(RelightError, match=r"nope\.png"):
        read_image(str(tmp_path / "nope.png"))
    corrupt = tmp_path / "corrupt.png"
    corrupt.write_bytes(b"this is not a png" * 10)
    with pytest.raises(RelightError, match=r"corrupt\.png"):
        read_image(str(corrupt))


def test_cache_reads_each_file_once(tmp_path):
    path = write_image(tmp_path / "c.exr", np.ones((2, 2, 3), np.float32), "float")
    cache = ImageCache()
    first = load_texture(path, cache, wrap_s="clamp", wrap_t="clamp")
    second = load_texture(path, cache, wrap_s="repeat", wrap_t="repeat", output="r")
    assert first.pixels is second.pixels


def test_use_metadata_wrap_modes(tmp_path):
    tagged = write_image(
        tmp_path / "w.exr", np.ones((2, 2, 3), np.float32), "float", [("wrapmodes", "periodic,mirror")]
    )
    untagged = write_image(tmp_path / "u.exr", np.ones((2, 2, 3), np.float32), "float")
    cache = ImageCache()
    texture = load_texture(tagged, cache)
    assert (texture.wrap_s, texture.wrap_t) == ("repeat", "mirror")
    texture = load_texture(untagged, cache)
    assert (texture.wrap_s, texture.wrap_t) == ("black", "black")
    with pytest.raises(RelightError, match="wrapS"):
        load_texture(untagged, cache, wrap_s="periodic")


# --- sampling ----------------------------------------------------------------------------------


def test_lower_left_convention():
    # Row 0 is the top: top-left 1, top-right 2, bottom-left 3, bottom-right 4.
    texture = texture_of([[[1.0], [2.0]], [[3.0], [4.0]]])
    uv = np.array([[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75], [0.5, 0.5]])
    np.testing.assert_allclose(sample_texture(texture, uv)[:, 0], [3.0, 4.0, 1.0, 2.0, 2.5])


# One row of four texels with values 1, 2, 3, 4; texel i has its centre at s = (i + 0.5) / 4.
# s = 0 lies halfway between texel -1 and texel 0; s = -0.125 is the centre of texel -1,
# s = -0.375 of texel -2, s = 1.125 of texel 4 and s = 0.25 halfway between texels 0 and 1.
_WRAP_CASES = {
    #            s = 0.125  0.25  0.0   -0.125  -0.375  1.125
    "repeat": [1.0, 1.5, 2.5, 4.0, 3.0, 1.0],
    "clamp": [1.0, 1.5, 1.0, 1.0, 1.0, 4.0],
    "mirror": [1.0, 1.5, 1.0, 1.0, 2.0, 4.0],
    "black": [1.0, 1.5, 0.5, 0.0, 0.0, 0.0],
}


@pytest.mark.parametrize("mode", sorted(_WRAP_CASES))
def test_wrap_modes_along_s(mode):
    texture = texture_of(np.array([[[1.0], [2.0], [3.0], [4.0]]]), wrap_s=mode, wrap_t="clamp")
    s = np.array([0.125, 0.25, 0.0, -0.125, -0.375, 1.125])
    uv = np.stack([s, np.full_like(s, 0.5)], axis=-1)
    np.testing.assert_allclose(sample_texture(texture, uv)[:, 0], _WRAP_CASES[mode], atol=1e-6)


@pytest.mark.parametrize("mode", sorted(_WRAP_CASES))
def test_wrap_modes_along_t(mode):
    # The same four values stacked bottom (t small) to top: row 0 (top) holds 4.
    texture = texture_of(np.array([[[4.0]], [[3.0]], [[2.0]], [[1.0]]]), wrap_s="clamp", wrap_t=mode)
    t = np.array([0.125, 0.25, 0.0, -0.125, -0.375, 1.125])
    uv = np.stack([np.full_like(t, 0.5), t], axis=-1)
    np.testing.assert_allclose(sample_texture(texture, uv)[:, 0], _WRAP_CASES[mode], atol=1e-6)


def test_channel_expansion():
    grey = texture_of([[[0.25]]])
    grey_alpha = texture_of([[[0.25, 0.5]]])
    rgb = texture_of([[[0.1, 0.2, 0.3]]])
    uv = np.array([[0.5, 0.5]])
    np.testing.assert_allclose(sample_texture(grey, uv), [[0.25, 0.25, 0.25, 1.0]])
    np.testing.assert_allclose(sample_texture(grey_alpha, uv), [[0.25, 0.25, 0.25, 0.5]])
    np.testing.assert_allclose(sample_texture(rgb, uv), [[0.1, 0.2, 0.3, 1.0]], rtol=1e-6)
    np.testing.assert_allclose(expand_to_rgba(np.array([[1.0, 2.0, 3.0, 4.0]])), [[1.0, 2.0, 3.0, 4.0]])


def test_scale_and_bias_as_for_a_normal_map():
    # An 8-bit normal map texel (0.5, 0.5, 1.0) with scale 2, bias -1 is the unperturbed (0, 0, 1).
    texture = texture_of(
        [[[0.5, 0.5, 1.0, 0.7]]],
        scale=np.array([2, 2, 2, 1], np.float32),
        bias=np.array([-1, -1, -1, 0], np.float32),
    )
    np.testing.assert_allclose(sample_texture(texture, np.array([[0.3, 0.6]])), [[0.0, 0.0, 1.0, 0.7]], atol=1e-6)


def test_st_from_uv_is_applied_before_lookup():
    # Scale u by 0.5: uv (0.75, 0.5) reads st (0.375, 0.5) = texel 1 of the 1 2 3 4 row.
    st_from_uv = np.diag([0.5, 1.0, 1.0])
    texture = texture_of(np.array([[[1.0], [2.0], [3.0], [4.0]]]), st_from_uv=st_from_uv)
    np.testing.assert_allclose(sample_texture(texture, np.array([[0.75, 0.5]]))[:, 0], [2.0])


def test_output_selection_and_channel_fitting():
    rgba = np.array([[0.1, 0.2, 0.3, 0.4]], np.float32)
    np.testing.assert_allclose(select_output(rgba, "rgb"), [[0.1, 0.2, 0.3]])
    np.testing.assert_allclose(select_output(rgba, "a"), [[0.4]])
    np.testing.assert_allclose(fit_channels(select_output(rgba, "g"), 3), [[0.2, 0.2, 0.2]])
    np.testing.assert_allclose(fit_channels(select_output(rgba, "rgb"), 1), [[0.1]])
