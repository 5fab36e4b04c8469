"""The project's two accuracy figures, defined once (DESIGN.md "Tests and measurement").

    PSNR   = 10 log10(1 / MSE) over all pixels and channels of linear RGB clamped to [0, 1]
    relMSE = mean((x - y)^2 / (y^2 + 0.01)), y the reference (unclamped)

Both take numpy arrays or torch tensors of the same shape (..., 3) and return Python floats.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import torch

# Images as either library holds them (or anything np.asarray takes).
_Image = npt.ArrayLike | torch.Tensor


def _as_float64(image: _Image) -> np.ndarray:
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu().numpy()
    return np.asarray(image, dtype=np.float64)


def _check_pair(image: _Image, reference: _Image) -> tuple[np.ndarray, np.ndarray]:
    x, y = _as_float64(image), _as_float64(reference)
    if x.shape != y.shape:
        raise ValueError(f"image shape {x.shape} differs from reference shape {y.shape}")
    return x, y


def psnr(image: _Image, reference: _Image) -> float:
    """PSNR in dB of `image` against `reference`; inf when they agree exactly after clamping."""
    x, y = _check_pair(image, reference)
    mse = float(np.mean((np.clip(x, 0.0, 1.0) - np.clip(y, 0.0, 1.0)) ** 2))
    return math.inf if mse == 0.0 else 10.0 * math.log10(1.0 / mse)


def rel_mse(image: _Image, reference: _Image) -> float:
    """Relative MSE of `image` against `reference`."""
    x, y = _check_pair(image, reference)
    return float(np.mean((x - y) ** 2 / (y * y + 0.01)))


def psnr_from_mse(mse: float) -> float:
    """The PSNR that a clamped-image MSE corresponds to (for noise budgets)."""
    return math.inf if mse <= 0.0 else 10.0 * math.log10(1.0 / mse)
