"""Image files read with OpenImageIO into linear float pixels (textures, light images, cookies).

Row 0 is the TOP of the image (numpy order). `read_image` decodes sRGB where `sourceColorSpace`
says so ('auto': 8-bit files with 3 or 4 channels are sRGB, everything else raw), the rule of the
UsdPreviewSurface spec for files without colour metadata.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import OpenImageIO as oiio

from relight_torch.errors import RelightError

COLOR_SPACES = ("auto", "raw", "sRGB")

# OIIO's `wrapmodes` metadata names ("s,t") for the UsdUVTexture wrap tokens.
_OIIO_WRAP_MODES = {"black": "black", "clamp": "clamp", "periodic": "repeat", "mirror": "mirror"}


def srgb_to_linear(encoded: np.ndarray) -> np.ndarray:
    """The exact sRGB EOTF (IEC 61966-2-1), piecewise linear below 0.04045.

    Args:
        encoded: any shape, sRGB-encoded values (nominally in [0, 1]).

    Returns:
        Same shape and dtype, linear values.
    """
    encoded = np.asarray(encoded)
    linear = np.where(
        encoded <= 0.04045,
        encoded / 12.92,
        ((np.maximum(encoded, 0.04045) + 0.055) / 1.055) ** 2.4,
    )
    return linear.astype(encoded.dtype, copy=False)


@dataclass(frozen=True)
class DecodedImage:
    """An image file read once, decoded to linear float pixels.

    Attributes:
        pixels: (H, W, C) float32 linear, C in 1..4, row 0 = top of the image.
        file_wrap_modes: (wrap_s, wrap_t) from the file's `wrapmodes` metadata, None where absent.
    """

    pixels: np.ndarray
    file_wrap_modes: tuple[str | None, str | None]


def read_image(path: str, source_color_space: str = "auto") -> DecodedImage:
    """Read an image file into linear float32 pixels.

    `sourceColorSpace` 'auto' decodes 8-bit images with 3 or 4 channels as sRGB and leaves
    everything else (16-bit, float, EXR, HDR, 1 or 2 channels) raw, per the spec's rule for files
    without colour metadata (OIIO tags every PNG and JPEG as sRGB, which says nothing about how the
    file was meant, so that tag is not used). Alpha is never decoded. More than 4 channels: the first
    4 are kept.

    Args:
        path: image file.
        source_color_space: 'auto', 'raw' or 'sRGB'.

    Returns:
        The decoded image.

    Raises:
        RelightError: the file is missing or not a readable image.
    """
    if source_color_space not in COLOR_SPACES:
        raise RelightError(f"texture {path}: unknown sourceColorSpace '{source_color_space}'")
    # Unassociated alpha: colour comes back as stored (PNG's straight alpha), not premultiplied.
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    image_input = oiio.ImageInput.open(path, config)
    if image_input is None:
        raise RelightError(f"cannot read image {path}: {oiio.geterror()}")
    try:
        spec = image_input.spec()
        pixels = image_input.read_image(format="float")
        if pixels is None:
            raise RelightError(f"cannot read image {path}: {image_input.geterror()}")
    finally:
        image_input.close()
    pixels = np.asarray(pixels, np.float32).reshape(spec.height, spec.width, -1)[..., :4]
    num_channels = pixels.shape[-1]
    is_srgb = source_color_space == "sRGB" or (
        source_color_space == "auto" and spec.format.basetype == oiio.UINT8 and num_channels in (3, 4)
    )
    if is_srgb:
        num_color = 1 if num_channels <= 2 else 3
        pixels = pixels.copy()
        pixels[..., :num_color] = srgb_to_linear(pixels[..., :num_color])
    wrap_names = spec.get_string_attribute("wrapmodes").split(",")
    wrap_s, wrap_t = (_OIIO_WRAP_MODES.get(name.strip()) for name in (wrap_names + [""])[:2])
    return DecodedImage(np.ascontiguousarray(pixels), (wrap_s, wrap_t))
