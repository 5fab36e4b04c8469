"""PNG previews for people: linear radiance -> clamp -> sRGB -> 8 bit (the only place we tone map)."""

from __future__ import annotations

import os

import numpy as np
import OpenImageIO as oiio

from relight_torch.io.atomic import atomic_path


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """sRGB encoding (IEC 61966-2-1) of linear values clamped to [0, 1]."""
    x = np.clip(linear, 0.0, 1.0)
    encoded: np.ndarray = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
    return encoded


def write_png(path: str | os.PathLike[str], linear_rgb: np.ndarray, exposure: float = 0.0) -> None:
    """Write an (H, W, 3) linear image as an 8-bit sRGB PNG, atomically.

    Args:
        exposure: stops applied before clamping (a display choice; the EXR keeps the data).
    """
    encoded = linear_to_srgb(np.asarray(linear_rgb, np.float64) * 2.0**exposure)
    pixels = np.round(encoded * 255.0).astype(np.uint8)
    height, width, channels = pixels.shape
    with atomic_path(path) as temp:
        output = oiio.ImageOutput.create(str(temp))
        if output is None:
            raise OSError(f"cannot create PNG writer for {path}: {oiio.geterror()}")
        output.open(str(temp), oiio.ImageSpec(width, height, channels, oiio.UINT8))
        output.write_image(pixels)
        output.close()
