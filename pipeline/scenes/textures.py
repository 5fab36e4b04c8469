"""Procedural images for the bundled scenes: a running-bond brick albedo and its matching normal map.

Both tile seamlessly (integer brick counts, wrap-around finite differences). Image arrays are
(H, W, C) with row 0 at the TOP, as written to the file; texture st (0, 0) is the image's
lower-left corner, so +t runs up the rows. The normal map is tangent space with +X along +s and
+Y along +t (the OpenGL / USD convention), encoded as (n + 1) / 2 in 8-bit and read back with
scale (2, 2, 2, 1), bias (-1, -1, -1, 0), sourceColorSpace 'raw'.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from relight_torch.io.atomic import atomic_path

BRICK_LINEAR_RGB = np.array([0.40, 0.11, 0.06])
"""Mean linear albedo of a brick (a mid red-brown)."""
MORTAR_LINEAR_RGB = np.array([0.45, 0.44, 0.40])
"""Linear albedo of the mortar."""


def brick_height(
    size: int, num_bricks_x: int, num_rows: int, *, mortar: float = 0.06, bevel: float = 0.05
) -> np.ndarray:
    """Height field of a running-bond brick wall, 0 in the mortar and 1 on the brick faces.

    Args:
        size: image size in pixels (square).
        num_bricks_x: bricks per row across the image.
        num_rows: brick rows down the image (even, so alternate rows tile).
        mortar: mortar joint width as a fraction of the brick height.
        bevel: width of the rounded brick edge, as a fraction of the brick height.

    Returns:
        (size, size) float32 heights in [0, 1].
    """
    row_f = (np.arange(size) + 0.5) / size * num_rows  # brick-row units
    col_f = (np.arange(size) + 0.5) / size * num_bricks_x  # brick-width units
    row_index = np.floor(row_f)[:, None]
    shifted = col_f[None, :] + 0.5 * (row_index % 2)  # half-brick offset every other row
    brick_aspect = (size / num_bricks_x) / (size / num_rows)  # brick width / height
    # Distance to the nearest joint, in brick heights.
    to_row_joint = 0.5 - np.abs(row_f[:, None] - row_index - 0.5)
    to_col_joint = (0.5 - np.abs(shifted - np.floor(shifted) - 0.5)) * brick_aspect
    inside = np.minimum(to_row_joint, to_col_joint) - 0.5 * mortar
    ramp = np.clip(inside / bevel, 0.0, 1.0)
    return (ramp * ramp * (3.0 - 2.0 * ramp)).astype(np.float32)  # smoothstep bevel


def brick_albedo(height: np.ndarray, num_bricks_x: int, num_rows: int, seed: int = 7) -> np.ndarray:
    """Linear albedo for `brick_height`: per-brick tint variation, mortar where the height is 0.

    Args:
        height: (S, S) heights from `brick_height` with the same brick counts.
        seed: seed of the per-brick variation.

    Returns:
        (S, S, 3) float32 linear RGB in [0, 1].
    """
    size = height.shape[0]
    rng = np.random.default_rng(seed)
    tints = rng.uniform(0.75, 1.2, size=(num_rows, num_bricks_x, 1)) * BRICK_LINEAR_RGB  # (rows, bricks, 3)
    row = (np.arange(size) * num_rows // size)[:, None]
    col_f = (np.arange(size) + 0.5) / size * num_bricks_x
    col = np.floor(col_f[None, :] + 0.5 * (row % 2)).astype(int) % num_bricks_x  # wrap: tiles seamlessly
    brick = tints[row, col, :]  # (S, S, 3)
    mix = np.clip(height * 4.0, 0.0, 1.0)[..., None]  # mortar -> brick quickly
    return np.clip(mix * brick + (1.0 - mix) * MORTAR_LINEAR_RGB, 0.0, 1.0).astype(np.float32)


def normal_map_from_height(height: np.ndarray, depth: float) -> np.ndarray:
    """Tangent-space normals of the surface z = depth * height(s, t) over the unit st square.

    Args:
        height: (S, S) heights, row 0 at the top (t = 1).
        depth: bump depth as a fraction of the texture's width.

    Returns:
        (S, S, 3) float32 unit normals, +X along +s, +Y along +t, +Z out of the surface.
    """
    size = height.shape[0]
    dh_ds = (np.roll(height, -1, axis=1) - np.roll(height, 1, axis=1)) * (0.5 * size)
    dh_dt = -(np.roll(height, -1, axis=0) - np.roll(height, 1, axis=0)) * (0.5 * size)  # rows run down
    normal = np.stack([-depth * dh_ds, -depth * dh_dt, np.ones_like(height)], axis=-1)
    return (normal / np.linalg.norm(normal, axis=-1, keepdims=True)).astype(np.float32)


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 transfer function: linear [0, 1] -> sRGB-encoded [0, 1]."""
    linear = np.clip(linear, 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1.0 / 2.4) - 0.055)


def write_png(path: Path, pixels: np.ndarray, *, color_space: str) -> Path:
    """Write (H, W, C) values in [0, 1] as an 8-bit PNG, atomically.

    Args:
        pixels: (H, W, C) float, already encoded (sRGB-encoded colour or raw data), row 0 at the top.
        color_space: 'sRGB' or 'Raw', recorded in the file's metadata.
    """
    quantized = np.round(np.clip(pixels, 0.0, 1.0) * 255.0).astype(np.uint8)
    spec = oiio.ImageSpec(quantized.shape[1], quantized.shape[0], quantized.shape[2], oiio.UINT8)
    spec.attribute("oiio:ColorSpace", color_space)
    with atomic_path(path) as temp:
        output = oiio.ImageOutput.create(str(temp))
        if output is None or not output.open(str(temp), spec) or not output.write_image(quantized):
            raise OSError(f"could not write {path}: {oiio.geterror()}")
        output.close()
    return path


def write_brick_textures(
    directory: Path, prefix: str, *, size: int = 512, num_bricks_x: int = 4, num_rows: int = 8, depth: float = 0.01
) -> tuple[Path, Path]:
    """Write <prefix>_brick_albedo.png (sRGB) and <prefix>_brick_normal.png (raw) into `directory`.

    Returns:
        (albedo path, normal map path).
    """
    height = brick_height(size, num_bricks_x, num_rows)
    albedo = brick_albedo(height, num_bricks_x, num_rows)
    normal = normal_map_from_height(height, depth)
    directory = Path(directory)
    return (
        write_png(directory / f"{prefix}_brick_albedo.png", srgb_encode(albedo), color_space="sRGB"),
        write_png(directory / f"{prefix}_brick_normal.png", 0.5 * (normal + 1.0), color_space="Raw"),
    )
