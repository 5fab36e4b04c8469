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
from relight_torch.multiview.correspondence import SAME_SURFACE_COS, ViewPoints

MAX_FILL_PIXELS = 2
# Neighbour offsets (drow, dcol) within two pixels, nearest first: the order a hole pixel tries them.
_OFFSETS = sorted(((dr, dc) for dr in range(-2, 3) for dc in range(-2, 3) if (dr, dc) != (0, 0)),
                  key=lambda o: (o[0] ** 2 + o[1] ** 2, o))


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


def fill_small_holes(view: ViewPoints, pool_row: torch.Tensor, pool: GBuffer,
                     max_fill_pixels: int = MAX_FILL_PIXELS) -> tuple[torch.Tensor, HoleReport]:
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
    rows = torch.full((height, width), -1, dtype=torch.int64, device=device)
    objects = torch.full((height, width), -1, dtype=torch.int64, device=device)
    rows.view(-1)[view.pixel_index] = pool_row
    objects.view(-1)[view.pixel_index] = view.object_id.to(torch.int64)
    normals = torch.zeros((height, width, 3), dtype=view.geometric_normal.dtype, device=device)
    normals.view(-1, 3)[view.pixel_index] = view.geometric_normal
    hole_image = (objects >= 0) & (rows < 0)
    labels, num_regions = ndimage.label(hole_image.cpu().numpy(), structure=np.ones((3, 3), bool))
    sizes = np.bincount(labels.reshape(-1), minlength=num_regions + 1)
    sizes[0] = 0
    large = torch.from_numpy(sizes[labels] > max_fill_pixels).to(device)
    todo = hole_image & ~large
    filled = rows.clone()
    for dr, dc in _OFFSETS:
        if not bool(todo.any()):
            break
        candidate = torch.full_like(rows, -1)
        target = (slice(max(dr, 0), height + min(dr, 0)), slice(max(dc, 0), width + min(dc, 0)))
        source = (slice(max(-dr, 0), height + min(-dr, 0)), slice(max(-dc, 0), width + min(-dc, 0)))
        # candidate[r, c] = rows[r - dr, c - dc]: the neighbour at offset (-dr, -dc).
        candidate[target] = rows[source]
        valid = candidate >= 0
        same_object = torch.zeros_like(valid)
        sample = candidate[valid]
        same_object[valid] = (pool.object_id[sample].to(torch.int64) == objects[valid]) & (
            (pool.geometric_normal[sample].to(normals.dtype) * normals[valid]).sum(-1) > SAME_SURFACE_COS)
        take = todo & same_object
        filled = torch.where(take, candidate, filled)
        todo = todo & ~take
    new_rows = filled.view(-1)[view.pixel_index]
    num_holes = int(hole_image.sum())
    report = HoleReport(
        num_points=view.num_points, num_holes=num_holes, num_filled=num_holes - int((new_rows < 0).sum()),
        num_large_holes=int(np.count_nonzero(sizes > max_fill_pixels)),
        large_pixel_index=torch.nonzero(large.view(-1)).squeeze(-1))
    return new_rows, report
