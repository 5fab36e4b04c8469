"""Bilinear resampling of the chosen caching camera's samples.

The correspondence map names, per point, a caching camera and the continuous position the point
projects to in its image. Nearest-pixel lookup (the paper's) snaps textures to the caching
camera's pixel grid: mortar lines of a brick floor come out jagged wherever the caching camera is
coarser than, or turned against, the new view. Here the four caching pixels around that position
are blended with bilinear weights: the nearest pixel (the correspondence's, of the point's own
surface) and its three neighbours towards the point, each kept only when it holds a sample of the
point's surface (the same object: `CachingViews.neighbours` lists a pool row's neighbours of its
object; a geometric normal within `SAME_SURFACE_COS` of the point's), weights renormalised over
those kept. Material parameters are blended where they
vary within a material (textures); flags, ids and per-material constants are the nearest pixel's.
The shading normal is the view's own smooth normal where the material does not perturb it, else
the cached normals' blend (only those points' normals are gathered); the tangent and bitangent
are built from that normal
(`math.frame.orthonormal_basis`): the BRDF is isotropic, so any tangent about the normal shades
alike (and a cached tangent may be zero where the mesh has no UVs).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import torch

from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.math.frame import orthonormal_basis
from relight_torch.multiview.views import (
    CONSTANT,
    PER_MATERIAL,
    SAME_SURFACE_COS,
    TEXTURED,
    CachingViews,
    neighbour_slot,
    take_rows,
    unpack_blend_columns,
)


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


def bilinear_samples(
    views: CachingViews,
    pixel: torch.Tensor,
    rows: torch.Tensor,
    normal: torch.Tensor,
    smooth: torch.Tensor | None = None,
    normal_mapped: torch.Tensor | None = None,
) -> Resampled:
    """The pool's samples around each point, blended (see the module docstring).

    Args:
        views: the caching cameras.
        pixel: (N, 2) continuous (column, row) of each point in its chosen camera's image (finite).
        rows: (N,) int64 the pool row of the pixel holding `pixel` (the correspondence's choice,
            which is the points' surface).
        normal: (N, 3) the points' unit geometric normals.
        smooth: (N, 3) the view's unit smooth normals, or None; normal_mapped: (num_materials,)
            bool, materials whose cached normals are kept. Either None keeps every cached normal.

    The other three taps are the nearest pixel's neighbours towards the point (`views.neighbours`:
    of the same object), kept where their geometric normal is within `SAME_SURFACE_COS` of the point's.
    """
    offset = pixel - torch.floor(pixel) - 0.5  # (N, 2) in [-0.5, 0.5)
    step = torch.where(offset >= 0, 1, -1)  # (N, 2) int64
    fraction = offset.abs()
    zero = torch.zeros_like(step[:, 0])
    slots = torch.stack(
        [neighbour_slot(zero, step[:, 0]), neighbour_slot(step[:, 1], zero), neighbour_slot(step[:, 1], step[:, 0])]
    )  # (3, N)
    count = views.neighbours.shape[1]
    others = views.neighbours.reshape(-1).index_select(0, (slots * count + rows).reshape(-1)).reshape(3, -1).long()
    cached = take_rows(views.surface_table[1:], others.clamp(min=0))  # (3, 3, N)
    others = torch.where(
        (others >= 0)
        & (cached[0] * normal[:, 0] + cached[1] * normal[:, 1] + cached[2] * normal[:, 2] > SAME_SURFACE_COS),
        others,
        -1,
    )
    tap = torch.cat([rows[None], others])  # (4, N)
    along, across = fraction[:, 0], fraction[:, 1]
    weight = torch.stack([(1 - along) * (1 - across), along * (1 - across), (1 - along) * across, along * across])
    weight = torch.where(tap >= 0, weight, 0.0)
    weight = weight / weight.sum(0)  # the nearest's weight is >= 1/4
    column_taps, column_weights = torch.where(tap >= 0, tap, rows), weight
    weight, safe = column_weights.T, column_taps.T
    sources = {
        TEXTURED: iter(_blend(views.blend_table, column_taps, column_weights)),
        PER_MATERIAL: iter(take_rows(views.material_table, rows)),
    }
    constant = views.blend_constants.tolist()
    blended = unpack_blend_columns(
        [
            next(sources[kind]) if kind != CONSTANT else weight.new_full((weight.shape[0],), constant[c])
            for c, kind in enumerate(views.blend_kind.tolist())
        ],
        views.pool,
    )
    pool = views.pool
    params = {
        f.name: blended[f.name] if f.name in blended else getattr(pool.params, f.name).index_select(0, rows)
        for f in dataclasses.fields(PreviewSurfaceParams)
    }
    material_id = pool.material_id.index_select(0, rows)
    if smooth is None or normal_mapped is None:
        shading = _blend(views.normal_table, column_taps, column_weights).T
    else:
        shading = smooth.to(views.normal_table.dtype).clone()
        kept = torch.nonzero(normal_mapped.index_select(0, material_id.long())).squeeze(-1)
        if kept.numel():
            shading.index_copy_(
                0,
                kept,
                _blend(views.normal_table, column_taps.index_select(1, kept), column_weights.index_select(1, kept)).T,
            )
    shading = torch.nn.functional.normalize(shading, dim=-1)
    tangent, bitangent = orthonormal_basis(shading)
    return Resampled(
        PreviewSurfaceParams(**params),
        shading,
        tangent,
        bitangent,
        material_id,
        pool.object_id.index_select(0, rows),
        safe,
        weight,
    )


def _blend(table: torch.Tensor, taps: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """(V, N) the (V, R) table's columns at `taps` (T, N) int64 rows, weighted by `weights` (T, N) and summed."""
    mixed = take_rows(table, taps[0]).mul_(weights[0])
    for t in range(1, taps.shape[0]):
        mixed.addcmul_(take_rows(table, taps[t]), weights[t])
    return mixed
