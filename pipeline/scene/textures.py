"""`UsdUVTexture` images: reading, colour decoding and bilinear sampling at texture coordinates.

Images are read with OpenImageIO (PNG, JPEG, EXR, Radiance HDR, anything OIIO reads) into linear
float32 pixels, row 0 at the top of the image, as `pipeline.scene.types.Texture` documents. Sampling
follows the UsdPreviewSurface spec (2.5) and Storm:

* st (0, 0) is the lower-left corner of the image, st (1, 1) the upper-right; texel (i, j) (column
  i, row j counted from the bottom) has its centre at st = ((i + 0.5) / W, (j + 0.5) / H).
* Bilinear filtering of the four nearest texel centres; the wrap mode is applied to each of the four
  integer texel indices (the OpenGL rule), so 'repeat' blends the last and first columns at s = 0,
  'clamp' and 'mirror' repeat the edge texel there, and 'black' blends towards zero
  (`relight_torch.math.texture.sample_bilinear`, shared with the opacity lookups of rays).
* Channels are expanded as UsdUVTexture outputs them: one channel -> (v, v, v, 1); two (grey and
  alpha) -> (v, v, v, a); three -> (r, g, b, 1).
* output = expanded sample * scale + bias.

Images packed inside a USDZ (or any Ar package) resolve to package-relative paths such as
`shot.usdz[textures/a.png]`; their bytes are read through Ar and decoded from a temporary file
(OpenImageIO's Python binding has no memory reader), and messages name the package path.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from pxr import Ar

from pipeline.errors import RelightError
from pipeline.scene.types import Texture
from relight_torch.io.images import DecodedImage, read_image
from relight_torch.math.texture import sample_bilinear

WRAP_MODES = ("black", "clamp", "repeat", "mirror")
OUTPUTS = ("rgb", "r", "g", "b", "a")

_OUTPUT_CHANNELS = {"rgb": slice(0, 3), "r": slice(0, 1), "g": slice(1, 2), "b": slice(2, 3), "a": slice(3, 4)}


class ImageCache:
    """Decoded images keyed by (path, sourceColorSpace), so each file is read once per library."""

    def __init__(self) -> None:
        self._images: dict[tuple[str, str], DecodedImage] = {}

    def read(self, path: str, source_color_space: str) -> DecodedImage:
        """`read_image` (or `read_packaged_image`), cached. Failures are not cached (they raise
        every time)."""
        key = (path, source_color_space)
        if key not in self._images:
            read = read_packaged_image if Ar.IsPackageRelativePath(path) else read_image
            self._images[key] = read(path, source_color_space)
        return self._images[key]


def read_packaged_image(path: str, source_color_space: str = "auto") -> DecodedImage:
    """`read_image` for an image inside a package, e.g. `/shots/a.usdz[textures/b.png]`.

    Raises:
        RelightError: the package or the image in it cannot be read (the message names `path`).
    """
    asset = Ar.GetResolver().OpenAsset(Ar.ResolvedPath(path))
    if asset is None:
        raise RelightError(f"cannot read image {path}: not found in its package")
    data = asset.GetBuffer()
    # Keep the packaged file's extension: OpenImageIO picks its reader by it.
    suffix = Path(Ar.SplitPackageRelativePathInner(path)[1]).suffix
    with tempfile.TemporaryDirectory(prefix="relight-package-") as directory:
        unpacked = Path(directory) / f"image{suffix}"
        unpacked.write_bytes(data)
        try:
            return read_image(str(unpacked), source_color_space)
        except RelightError as error:
            raise RelightError(str(error).replace(str(unpacked), path)) from None


def load_texture(
    path: str,
    cache: ImageCache,
    *,
    source_color_space: str = "auto",
    wrap_s: str = "useMetadata",
    wrap_t: str = "useMetadata",
    scale: np.ndarray | None = None,
    bias: np.ndarray | None = None,
    fallback: np.ndarray | None = None,
    output: str = "rgb",
    st_primvar: str = "st",
    st_from_uv: np.ndarray | None = None,
) -> Texture:
    """Build a `Texture` from a UsdUVTexture node's settings, reading the image through `cache`.

    Args:
        path: resolved image path.
        cache: the library's image cache.
        source_color_space: 'auto', 'raw' or 'sRGB'.
        wrap_s, wrap_t: a `WRAP_MODES` token or 'useMetadata' (the file's `wrapmodes`, else black).
        scale, bias, fallback: (4,) RGBA; None for the UsdUVTexture fallbacks (1, 0, (0, 0, 0, 1)).
        output: the connected output, one of `OUTPUTS`.
        st_primvar: primvar feeding the st input.
        st_from_uv: (3, 3) affine map from the primvar to st; None for identity.

    Returns:
        The texture, pixels decoded.

    Raises:
        RelightError: unreadable file, or an unknown wrap / colour space / output token.
    """
    for name, token in (("wrapS", wrap_s), ("wrapT", wrap_t)):
        if token not in WRAP_MODES + ("useMetadata",):
            raise RelightError(f"texture {path}: unknown {name} '{token}'")
    if output not in OUTPUTS:
        raise RelightError(f"texture {path}: unknown output '{output}'")
    image = cache.read(path, source_color_space)
    default = Texture(file=path, pixels=image.pixels)
    wrap_modes = [
        token if token != "useMetadata" else (file_mode or "black")
        for token, file_mode in zip((wrap_s, wrap_t), image.file_wrap_modes, strict=True)
    ]
    return Texture(
        file=path,
        pixels=image.pixels,
        wrap_s=wrap_modes[0],
        wrap_t=wrap_modes[1],
        scale=default.scale if scale is None else np.asarray(scale, np.float32),
        bias=default.bias if bias is None else np.asarray(bias, np.float32),
        fallback=default.fallback if fallback is None else np.asarray(fallback, np.float32),
        output=output,
        st_primvar=st_primvar,
        st_from_uv=default.st_from_uv if st_from_uv is None else np.asarray(st_from_uv, np.float64),
    )


def expand_to_rgba(values: np.ndarray) -> np.ndarray:
    """Expand (..., C) texel values to RGBA the way UsdUVTexture outputs them.

    Args:
        values: (..., C), C in 1..4.

    Returns:
        (..., 4): C=1 -> (v, v, v, 1); C=2 -> (v, v, v, a); C=3 -> (r, g, b, 1); C=4 unchanged.
    """
    num_channels = values.shape[-1]
    ones = np.ones(values.shape[:-1] + (1,), values.dtype)
    if num_channels == 1:
        return np.concatenate([values, values, values, ones], axis=-1)
    if num_channels == 2:
        grey = values[..., :1]
        return np.concatenate([grey, grey, grey, values[..., 1:2]], axis=-1)
    if num_channels == 3:
        return np.concatenate([values, ones], axis=-1)
    return values


def select_output(rgba: np.ndarray, output: str) -> np.ndarray:
    """The channels of a UsdUVTexture output: (..., 4) -> (..., 3) for 'rgb', (..., 1) for r/g/b/a."""
    return rgba[..., _OUTPUT_CHANNELS[output]]


def fit_channels(values: np.ndarray, num_channels: int) -> np.ndarray:
    """Adapt (..., K) values to an input of `num_channels` (USD's connection type conversions).

    One channel is broadcast (a float output feeding a colour); a wider value keeps its first
    `num_channels` (an rgb output feeding a float takes r); a narrower one is zero-padded.
    """
    width = values.shape[-1]
    if width == num_channels:
        return values
    if width == 1:
        return np.repeat(values, num_channels, axis=-1)
    if width > num_channels:
        return values[..., :num_channels]
    padding = np.zeros(values.shape[:-1] + (num_channels - width,), values.dtype)
    return np.concatenate([values, padding], axis=-1)


def sample_texture(texture: Texture, uv: np.ndarray) -> np.ndarray:
    """Bilinearly sample a texture at primvar coordinates.

    Args:
        texture: the texture (pixels row 0 = top).
        uv: (N, 2) values of `texture.st_primvar`; `texture.st_from_uv` maps them to st.

    Returns:
        (N, 4) float32 RGBA = expanded sample * scale + bias (not yet reduced to `texture.output`).
    """
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    st = uv @ texture.st_from_uv[:2, :2].T + texture.st_from_uv[:2, 2]
    sampled = sample_bilinear(texture.pixels, st, texture.wrap_s, texture.wrap_t)
    return expand_to_rgba(sampled) * texture.scale + texture.bias
