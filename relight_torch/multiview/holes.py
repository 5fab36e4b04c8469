"""Holes of the correspondence map: points of the new view that no caching camera sees.

Holes are grouped into 8-connected regions of the new view's sub-sample image. Regions of at most
`max_fill_pixels` pixels (the paper's one- or two-pixel holes) take the sample of the nearest
neighbour (within two pixels, nearest first) whose sample is of the same surface (as the
correspondence map checks it: same object, geometric normals within `SAME_SURFACE_COS`); the
position stays the new view's own, so only the material and shading frame are borrowed. Larger
regions are reported, with their pixels, for the caller to fill with a small on-demand bake
(`pipeline.bake.multiview.holes`) or to leave black.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from relight_torch.gbuffer import GBuffer
from relight_torch.multiview.correspondence import ViewPoints
from relight_torch.multiview.views import SAME_SURFACE_COS

MAX_FILL_PIXELS = 2
# Neighbour offsets (drow, dcol) within two pixels, nearest first: the order a hole pixel tries them.
_OFFSETS = sorted(
    ((dr, dc) for dr in range(-2, 3) for dc in range(-2, 3) if (dr, dc) != (0, 0)),
    key=lambda o: (o[0] ** 2 + o[1] ** 2, o),
)


@dataclass(frozen=True)
class HoleReport:
    """What the correspondence map left uncovered in one new view.

    Attributes:
        num_points: sub-samples of the new view that see a surface.
        num_holes: of those, how many no caching camera sees.
        num_filled: holes filled from a neighbour.
        num_large_holes: connected hole regions larger than the fill size.
        large_pixel_index: (M,) int64 flat sub-sample indices of the pixels of those regions.
    """

    num_points: int
    num_holes: int
    num_filled: int
    num_large_holes: int
    large_pixel_index: torch.Tensor

    @property
    def hole_fraction_before(self) -> float:
        return self.num_holes / max(self.num_points, 1)

    @property
    def hole_fraction_after(self) -> float:
        return (self.num_holes - self.num_filled) / max(self.num_points, 1)


def fill_small_holes(
    view: ViewPoints, pool_row: torch.Tensor, pool: GBuffer, max_fill_pixels: int = MAX_FILL_PIXELS
) -> tuple[torch.Tensor, HoleReport]:
    """Fill small holes of a correspondence from their neighbours.

    Args:
        view: the new view's points (N of them).
        pool_row: (N,) int64 chosen pool row per point, -1 for holes.
        pool: the samples pool_row indexes (`CachingViews.pool`).
        max_fill_pixels: regions of at most this many pixels are filled.

    Returns:
        ((N,) int64 pool rows with small holes filled, the report).
    """
    height, width = view.image_size
    device = pool_row.device
    slot = torch.full((height * width,), -1, dtype=torch.int64, device=device)  # point of each pixel
    slot[view.pixel_index] = torch.arange(view.num_points, device=device)
    hole_points = torch.nonzero(pool_row < 0).squeeze(-1)
    hole_image = np.zeros(height * width, bool)
    hole_image[view.pixel_index[hole_points].cpu().numpy()] = True
    labels, num_regions = ndimage.label(hole_image.reshape(height, width), structure=np.ones((3, 3), bool))
    sizes = np.bincount(labels.reshape(-1), minlength=num_regions + 1)
    sizes[0] = 0
    large = torch.from_numpy(sizes[labels.reshape(-1)] > max_fill_pixels).to(device)
    # Only the small holes' points are visited, one neighbour offset at a time.
    todo = hole_points[~large[view.pixel_index[hole_points]]]
    filled = pool_row.clone()
    for dr, dc in _OFFSETS:
        if todo.numel() == 0:
            break
        pixel = view.pixel_index[todo]
        row, column = pixel // width + dr, pixel % width + dc
        inside = (row >= 0) & (row < height) & (column >= 0) & (column < width)
        neighbour = slot[torch.where(inside, row * width + column, torch.zeros_like(pixel))]
        sample = torch.where(inside & (neighbour >= 0), pool_row[neighbour.clamp(min=0)], -torch.ones_like(pixel))
        safe = sample.clamp(min=0)
        take = (
            (sample >= 0)
            & (pool.object_id[safe].to(torch.int64) == view.object_id[todo].to(torch.int64))
            & (
                (pool.geometric_normal[safe].to(view.geometric_normal.dtype) * view.geometric_normal[todo]).sum(-1)
                > SAME_SURFACE_COS
            )
        )
        filled[todo[take]] = sample[take]
        todo = todo[~take]
    num_holes = int(hole_points.numel())
    report = HoleReport(
        num_points=view.num_points,
        num_holes=num_holes,
        num_filled=num_holes - int((filled < 0).sum()),
        num_large_holes=int(np.count_nonzero(sizes > max_fill_pixels)),
        large_pixel_index=torch.nonzero(large).squeeze(-1),
    )
    return filled, report
