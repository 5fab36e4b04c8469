"""Measured spectra to linear Rec.709 RGB (the project's rendering space), in one documented place.

Method (CIE 015:2018 section 7, with the tables in `cie_data`):

* A spectrum tabulated at its own wavelengths is resampled onto the 5 nm grid 380-780 nm by linear
  interpolation, holding the end values outside the measured range (the Cornell data stop at 400
  and 700 nm; less than 0.4 % of any colour matching function lies outside that range).
* Reflectance under illuminant D65: XYZ = sum(R S cmf) / sum(S y_bar), so a perfect white
  reflector has Y = 1 and the chromaticity of D65.
* Emission: XYZ = sum(L cmf), then divided by Y so the colour has unit luminance (the spectrum's
  absolute scale becomes the light's `intensity`).
* XYZ -> linear RGB uses the Rec.709 / sRGB primaries (x, y) = (0.64, 0.33), (0.30, 0.60),
  (0.15, 0.06) with the D65 white point computed from the same tables, so a perfect reflector
  maps to RGB (1, 1, 1) exactly. The matrix agrees with IEC 61966-2-1's rounded one to 1e-3.
"""

from __future__ import annotations

import numpy as np

from pipeline.scenes.cie_data import CIE_1931_D65_5NM

_TABLE = np.asarray(CIE_1931_D65_5NM, np.float64)
WAVELENGTHS_NM = _TABLE[:, 0]
"""(81,) float64 grid of the tables, 380-780 nm in 5 nm steps."""
CMF_XYZ = _TABLE[:, 1:4]
"""(81, 3) float64 CIE 1931 2-degree colour matching functions x_bar, y_bar, z_bar."""
D65 = _TABLE[:, 4]
"""(81,) float64 relative spectral power of CIE illuminant D65 (100 at 560 nm)."""

REC709_PRIMARIES_XY = np.array([[0.64, 0.33], [0.30, 0.60], [0.15, 0.06]])
"""(3, 2) chromaticities of the R, G, B primaries of ITU-R BT.709 (= sRGB)."""


def resample_spectrum(wavelengths_nm: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Linearly interpolate a tabulated spectrum onto `WAVELENGTHS_NM`, holding the end values.

    Args:
        wavelengths_nm: (K,) increasing sample wavelengths in nm.
        values: (K,) spectrum at those wavelengths.

    Returns:
        (81,) float64 spectrum on the 5 nm grid 380-780 nm.
    """
    return np.interp(WAVELENGTHS_NM, np.asarray(wavelengths_nm, np.float64), np.asarray(values, np.float64))


def _xyz_white_d65() -> np.ndarray:
    """(3,) XYZ of a perfect reflector under D65, normalised to Y = 1."""
    xyz = D65 @ CMF_XYZ
    return xyz / xyz[1]


def linear_rec709_from_xyz_matrix() -> np.ndarray:
    """The (3, 3) matrix taking CIE XYZ (column vector) to linear Rec.709 RGB with a D65 white.

    Built the textbook way (SMPTE RP 177): columns of the primaries' XYZ at unit Y, scaled so
    their sum is the white point, then inverted.
    """
    x, y = REC709_PRIMARIES_XY[:, 0], REC709_PRIMARIES_XY[:, 1]
    xyz_from_rgb_unscaled = np.stack([x / y, np.ones(3), (1.0 - x - y) / y])  # (3, 3) columns = primaries
    scale = np.linalg.solve(xyz_from_rgb_unscaled, _xyz_white_d65())
    return np.linalg.inv(xyz_from_rgb_unscaled * scale)


def reflectance_to_linear_rec709(wavelengths_nm: np.ndarray, reflectance: np.ndarray) -> np.ndarray:
    """Linear Rec.709 RGB of a diffuse reflector seen under D65 (perfect white -> (1, 1, 1)).

    Args:
        wavelengths_nm: (K,) sample wavelengths in nm.
        reflectance: (K,) spectral reflectance in [0, 1].

    Returns:
        (3,) float64 linear RGB albedo.
    """
    weights = D65[:, None] * CMF_XYZ  # (81, 3)
    xyz = resample_spectrum(wavelengths_nm, reflectance) @ weights / (D65 @ CMF_XYZ[:, 1])
    return linear_rec709_from_xyz_matrix() @ xyz


def emission_to_linear_rec709(wavelengths_nm: np.ndarray, radiance: np.ndarray) -> np.ndarray:
    """Linear Rec.709 colour of an emission spectrum, normalised to unit luminance (Y = 1).

    Args:
        wavelengths_nm: (K,) sample wavelengths in nm.
        radiance: (K,) relative spectral radiance (any scale).

    Returns:
        (3,) float64 RGB with 0.2126 R + 0.7152 G + 0.0722 B = 1 (up to the primaries' rounding).
    """
    xyz = resample_spectrum(wavelengths_nm, radiance) @ CMF_XYZ
    return linear_rec709_from_xyz_matrix() @ (xyz / xyz[1])
