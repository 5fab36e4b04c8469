"""Bilinear resampling of the chosen caching camera's samples.

The correspondence map names, per point, a caching camera and the continuous position the point
projects to in its image. Nearest-pixel lookup (the paper's) snaps textures to the caching
camera's pixel grid: mortar lines of a brick floor come out jagged wherever the caching camera is
coarser than, or turned against, the new view. Here the four caching pixels around that position
are blended with bilinear weights, each kept only when it holds a sample of the same surface as
the point (same object, geometric normal within `SAME_SURFACE_COS`; the nearest pixel is one of
the four and always qualifies), weights renormalised over those kept. Material parameters and
the shading normal and tangent are blended (the frame re-orthonormalised), flags and ids are the
nearest pixel's.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import torch

from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.multiview.correspondence import same_surface
from relight_torch.multiview.views import CachingViews, take_rows, take_small, unpack_blend_table

_TAPS = torch.tensor([[0, 0], [1, 0], [0, 1], [1, 1]])


class Resampled(NamedTuple):
    """N resampled samples: material, shading frame (N, 3) each, the nearest pixel's ids (N,), and
    the blend itself: `taps` (N, 4) int64 pool rows and their `weights` (N, 4) float32 (summing to 1),
    with which the samples' cached lighting is blended too (`multiview.incident`)."""

    params: PreviewSurfaceParams
    normal: torch.Tensor
    tangent: torch.Tensor
    bitangent: torch.Tensor
    material_id: torch.Tensor
    object_id: torch.Tensor
    taps: torch.Tensor
    weights: torch.Tensor


def bilinear_samples(views: CachingViews, view_index: torch.Tensor, pixel: torch.Tensor, rows: torch.Tensor,
                     object_id: torch.Tensor, normal: torch.Tensor) -> Resampled:
    """The pool's samples around each point, blended (see the module docstring).

    Args:
        views: the caching cameras.
        view_index: (N,) int64 chosen camera per point.
        pixel: (N, 2) continuous (column, row) in that camera's image (finite).
        rows: (N,) int64 the nearest pixel's pool row (the correspondence's choice).
        object_id: (N,) object of each point; normal: (N, 3) its unit geometric normal.
    """
    size = take_small(views.sizes.T.contiguous(), view_index)
    height, width = size[0][:, None], size[1][:, None]
    corner = pixel - 0.5
    base = torch.floor(corner)
    fraction = corner - base
    taps = _TAPS.to(pixel.device)
    column = base[:, 0, None].long() + taps[:, 0]                                   # (N, 4)
    line = base[:, 1, None].long() + taps[:, 1]
    inside = (column >= 0) & (column < width) & (line >= 0) & (line < height)
    flat = torch.where(inside, line * width + column, torch.zeros_like(column)) + views.image_offsets.index_select(
        0, view_index)[:, None]
    sample = torch.where(inside, take_rows(views.pool_row[None], flat)[0], torch.full_like(flat, -1))
    safe = sample.clamp(min=0)
    same = (sample >= 0) & same_surface(take_rows(views.surface_table, safe), object_id.float()[:, None],
                                        normal[:, None])
    along = torch.where(taps[:, 0].bool(), fraction[:, 0, None], 1 - fraction[:, 0, None])
    across = torch.where(taps[:, 1].bool(), fraction[:, 1, None], 1 - fraction[:, 1, None])
    weight = torch.where(same, along * across, torch.zeros_like(along))
    total = weight.sum(-1, keepdim=True)
    # Where no tap qualifies (rounding at an image edge), the nearest sample alone.
    weight = torch.where(total > 0, weight / total.clamp(min=1e-12), taps.new_tensor([1.0, 0, 0, 0]).to(weight))
    safe = torch.where(total > 0, safe, rows[:, None].expand_as(safe))
    # Tap by tap, whole (V, N) slabs times contiguous (N,) weights.
    column_weights, column_taps = weight.T.contiguous(), safe.T.contiguous()
    mixed = take_rows(views.blend_table, column_taps[0]).mul_(column_weights[0])                   # (V, N)
    for t in range(1, taps.shape[0]):
        mixed.addcmul_(take_rows(views.blend_table, column_taps[t]), column_weights[t])
    packed = views.blend_constants.expand(weight.shape[0], -1).clone()
    packed.index_copy_(1, torch.nonzero(views.blend_columns).squeeze(-1), mixed.T)
    blended = unpack_blend_table(packed, views.pool)
    pool = views.pool
    params = {f.name: blended[f.name] if f.name in blended else getattr(pool.params, f.name).index_select(0, rows)
              for f in dataclasses.fields(PreviewSurfaceParams)}
    shading = torch.nn.functional.normalize(blended["normal"], dim=-1)
    tangent = blended["tangent"]
    tangent = torch.nn.functional.normalize(tangent - shading * (tangent * shading).sum(-1, keepdim=True), dim=-1)
    return Resampled(PreviewSurfaceParams(**params), shading, tangent, torch.cross(shading, tangent, dim=-1),
                     pool.material_id.index_select(0, rows), pool.object_id.index_select(0, rows), safe, weight)
