"""The 2-D Haar wavelet transform of square images (GPU Gems 3 ch. 9, Listing 9-4), in torch.

Non-standard decomposition with the chapter's 0.5 weights, which make it orthonormal: at each
level the top-left `side x side` block of 2 x 2 cells becomes box / horizontal / vertical /
diagonal coefficients placed in its four quadrants, then the box quadrant is transformed again.
With a[i, j] (row i, column j) and h = side / 2:

    out[i/2,     j/2    ] = 0.5 (a[i, j] + a[i+1, j] + a[i, j+1] + a[i+1, j+1])    box
    out[i/2,     j/2 + h] = 0.5 (a[i, j] - a[i+1, j] + a[i, j+1] - a[i+1, j+1])    horizontal
    out[i/2 + h, j/2    ] = 0.5 (a[i, j] + a[i+1, j] - a[i, j+1] - a[i+1, j+1])    vertical
    out[i/2 + h, j/2 + h] = 0.5 (a[i, j] - a[i+1, j] - a[i, j+1] + a[i+1, j+1])    diagonal

Because the transform is orthonormal, a row r of a transfer matrix and a light vector g satisfy
r . g = haar(r) . haar(g): the relighter multiplies wavelet rows by the wavelet light.
"""

from __future__ import annotations

import torch


def _check_square(image: torch.Tensor) -> int:
    """Side n of (..., n, n, C) images, n a power of two; raises ValueError otherwise."""
    if image.dim() < 3 or image.shape[-3] != image.shape[-2]:
        raise ValueError(f"expected (..., n, n, C) square images, got {tuple(image.shape)}")
    side = int(image.shape[-3])
    if side < 1 or side & (side - 1):
        raise ValueError(f"image side must be a power of two, got {side}")
    return side


def haar2d(image: torch.Tensor) -> torch.Tensor:
    """Forward 2-D Haar transform.

    Args:
        image: (..., n, n, C) with n a power of two (channels last).

    Returns:
        (..., n, n, C) coefficients, laid out as in the module doc (dtype and device of `image`).
    """
    side = _check_square(image)
    out = image.clone()
    while side >= 2:
        half = side // 2
        # View the block as (..., h, 2 rows, h, 2 columns, C): one pass per level, no strided writes.
        cells = out[..., :side, :side, :].reshape(*out.shape[:-3], half, 2, half, 2, out.shape[-1])
        top, bottom = cells[..., 0, :, :, :], cells[..., 1, :, :, :]
        row_sum, row_difference = top + bottom, top - bottom
        box = 0.5 * (row_sum[..., 0, :] + row_sum[..., 1, :])
        horizontal = 0.5 * (row_difference[..., 0, :] + row_difference[..., 1, :])
        vertical = 0.5 * (row_sum[..., 0, :] - row_sum[..., 1, :])
        diagonal = 0.5 * (row_difference[..., 0, :] - row_difference[..., 1, :])
        out[..., :side, :side, :] = torch.cat(
            [torch.cat([box, horizontal], dim=-2), torch.cat([vertical, diagonal], dim=-2)], dim=-3
        )
        side = half
    return out


def inverse_haar2d(coefficients: torch.Tensor) -> torch.Tensor:
    """Inverse of `haar2d` (its transpose, the transform being orthonormal).

    Args:
        coefficients: (..., n, n, C) as returned by `haar2d`.

    Returns:
        (..., n, n, C) image.
    """
    full = _check_square(coefficients)
    out = coefficients.clone()
    side = 2
    while side <= full:
        half = side // 2
        box = out[..., :half, :half, :].clone()
        horizontal = out[..., :half, half:side, :].clone()
        vertical = out[..., half:side, :half, :].clone()
        diagonal = out[..., half:side, half:side, :].clone()
        block = out[..., :side, :side, :]
        block[..., 0::2, 0::2, :] = 0.5 * (box + horizontal + vertical + diagonal)
        block[..., 1::2, 0::2, :] = 0.5 * (box - horizontal + vertical - diagonal)
        block[..., 0::2, 1::2, :] = 0.5 * (box + horizontal - vertical - diagonal)
        block[..., 1::2, 1::2, :] = 0.5 * (box - horizontal - vertical + diagonal)
        side *= 2
    return out


def support_area(side: int, device: torch.device | str | None = None) -> torch.Tensor:
    """(n, n) int64 number of pixels each coefficient's basis function covers (Listing 9-5).

    The coefficient at (i, j) with m = max(i, j) >= 1 belongs to the level whose quadrants are
    2^floor(log2 m) wide, and covers (n / 2^floor(log2 m))^2 pixels; the box coefficient (0, 0)
    covers all n^2 (the chapter's table gives it 4 n^2; either way it ranks first).
    """
    index = torch.arange(side, device=device)
    m = torch.maximum(index[:, None], index[None, :])
    quadrant_width = torch.pow(2, torch.floor(torch.log2(m.clamp(min=1).double()))).long()
    return torch.where(m > 0, (side // quadrant_width) ** 2, side * side)
