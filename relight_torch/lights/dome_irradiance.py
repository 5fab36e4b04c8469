"""A dome light's unshadowed irradiance per surface normal: the closed form of its ratio estimator.

E_c(n) = integral of T_c(w) max(0, n.w) dw over the sphere, T the lat-long image (1 for an
untextured dome: E = pi), is tabulated once per image over normals on a lat-long grid and looked
up bilinearly: a prefiltered irradiance environment map (Miller & Hoffman 1984; Greene 1986), here
computed exactly rather than in spherical harmonics (Ramamoorthi & Hanrahan 2001), whose nine
terms miss a small bright sun by several per cent.

The image is first reduced to blocks of texels. Each block keeps, per channel, the vector
D = sum_t T_t w_t dw_t over its texels, so that max(0, n.D) is the block's exact contribution
wherever the whole block is above the normal's horizon (the integrand is linear in w there);
only blocks that the horizon crosses are approximated. The texels are those the sampler looks up
(nearest, `dome.DomeSampler`), so the table is what the Monte Carlo estimate tends to.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from relight_torch.lights.dome import latlong_coordinates, latlong_direction

# The table's normals: rows from pole to pole inclusive, columns around the sphere, both ends kept
# (the first column repeated) so that a bilinear lookup wraps.
TABLE_ROWS, TABLE_COLUMNS = 64, 128
# The most blocks the image is reduced to (rows, columns): the table's cost is their count times
# its normals'.
MAX_BLOCK_ROWS, MAX_BLOCK_COLUMNS = 64, 128
# Normals per matrix product while the table is made: bounds its temporaries to ~100 MB.
NORMALS_PER_PASS = 1024


@dataclass(frozen=True)
class DomeIrradiance:
    """Per-channel irradiance of a unit-scale lat-long image, by normal in its lookup frame.

    Attributes:
        table: (3, TABLE_ROWS + 1, TABLE_COLUMNS + 1) E_c at normals on the lat-long grid
            (row 0 the +Y pole, column 0 at u = 0), on the caller's device and dtype.
    """

    table: torch.Tensor

    @staticmethod
    def build(texture: np.ndarray, device: torch.device, dtype: torch.dtype) -> DomeIrradiance:
        """The table of a (H, W, 3) lat-long image (row 0 the top pole), made in float64."""
        blocks = _block_vectors(np.asarray(texture, np.float64))  # (B, 3 channels, 3)
        rows = torch.linspace(0.0, 1.0, TABLE_ROWS + 1, dtype=torch.float64)
        columns = torch.linspace(0.0, 1.0, TABLE_COLUMNS + 1, dtype=torch.float64)
        v, u = torch.meshgrid(rows, columns, indexing="ij")
        normals = latlong_direction(u, v).reshape(-1, 3)
        vectors = torch.as_tensor(blocks, dtype=torch.float64).permute(2, 0, 1).reshape(3, -1)  # (3, B * 3)
        table = torch.empty(normals.shape[0], 3, dtype=torch.float64)
        for start in range(0, normals.shape[0], NORMALS_PER_PASS):
            cosines = (normals[start : start + NORMALS_PER_PASS] @ vectors).clamp_(min=0.0)
            table[start : start + NORMALS_PER_PASS] = cosines.reshape(cosines.shape[0], -1, 3).sum(1)
        table = table.T.reshape(3, TABLE_ROWS + 1, TABLE_COLUMNS + 1)
        return DomeIrradiance(table.to(device=device, dtype=dtype))

    def irradiance(self, normals_lookup: torch.Tensor) -> torch.Tensor:
        """(..., 3) E at unit normals (..., 3) of the lookup frame, bilinear between the table's."""
        u, v_from_top = latlong_coordinates(normals_lookup)
        # align_corners=True: -1 and 1 are the first and last rows and columns (the poles, u = 0 and 1).
        grid = torch.stack((2.0 * u - 1.0, 2.0 * v_from_top - 1.0), dim=-1).reshape(1, 1, -1, 2)
        looked_up = torch.nn.functional.grid_sample(self.table.unsqueeze(0), grid, mode="bilinear", align_corners=True)
        return looked_up.reshape(3, -1).T.reshape(*normals_lookup.shape[:-1], 3)


def _block_vectors(texture: np.ndarray) -> np.ndarray:
    """(B, 3, 3): per block of texels and channel c, sum_t T_c w_t dw_t (a vector, module doc)."""
    height, width = texture.shape[:2]
    # Exact solid angles of the texels: a band of rows between two polar angles, cut in columns.
    edges = np.cos(np.arange(height + 1) / height * math.pi)
    solid_angle = (edges[:-1] - edges[1:]) * (2.0 * math.pi / width)  # (H,)
    # Each texel's direction at its centre: the sampler's nearest lookup gives it this value.
    v, u = np.meshgrid((np.arange(height) + 0.5) / height, (np.arange(width) + 0.5) / width, indexing="ij")
    directions = latlong_direction(torch.as_tensor(u), torch.as_tensor(v)).numpy()  # (H, W, 3)
    row_starts = _block_starts(height, MAX_BLOCK_ROWS)
    column_starts = _block_starts(width, MAX_BLOCK_COLUMNS)
    blocks = np.empty((row_starts.size, column_starts.size, 3, 3))
    # One (H, W) product at a time: a 4k image's (H, W, 3, 3) would take 600 MB.
    for channel in range(3):
        power = texture[..., channel] * solid_angle[:, None]
        for axis in range(3):
            rows = np.add.reduceat(power * directions[..., axis], row_starts, axis=0)
            blocks[..., channel, axis] = np.add.reduceat(rows, column_starts, axis=1)
    return blocks.reshape(-1, 3, 3)


def _block_starts(size: int, most: int) -> np.ndarray:
    """The first index of each of min(size, most) near-equal consecutive blocks of `size` items."""
    return np.array([group[0] for group in np.array_split(np.arange(size), min(size, most))])
