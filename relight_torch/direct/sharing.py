"""Light shared by the sub-samples of a pixel that lie on one surface.

A deep framebuffer keeps s x s sub-samples per pixel so that edges and textures are antialiased;
the light reaching them varies far more slowly across a pixel than the material or the coverage
does. Decoupled sampling (Ragan-Kelley, Lehtinen, Chen, Doggett & Durand 2011) shades at a
coarser rate than it samples visibility and materials: here the light a sub-sample receives (its
light samples, shadow rays and BRDF factors) is evaluated once per group of sub-samples of one
pixel on one surface, at the group's centroid (`PixelGroups`), and every sub-sample of the group
then combines it with its own material colours. At 2 x 2 supersampling that is a quarter of
the light samples and shadow rays of a light edit wherever a pixel sees one surface.

A group is one pixel's sub-samples with the owner's object and material, shading normals within
`SHARED_NORMAL_COSINE` of the owner's, and lying near the owner's tangent plane (the surface
filter's `MAX_PLANE_SLOPE`): a silhouette, a crease or a normal-mapped bump keeps its sub-samples
apart. A group's *owner* is its first sub-sample in the pixel's row-major order (its fixed light
samples are the group's), so a pixel's top-left sub-sample owns its group: the progressive
levels' points (`relight_torch.levels`) are owners.
"""

from __future__ import annotations

import copy
import dataclasses
import math

import torch

from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.gbuffer import GBuffer
from relight_torch.math.frame import dot
from relight_torch.visibility.surface_filter import MAX_PLANE_SLOPE, FilterGrid, SurfaceFilter

SHARED_NORMAL_COSINE = 0.995
"""Sub-samples whose shading normals are further apart (~5.7 degrees) light separately: a glossy
highlight moves that much across a pixel only on a surface curved within it."""
MIN_LIFT_COSINE = 0.5
"""A sub-sample's facet tilted further from its group's mean normal lifts it as if at 60 degrees."""


def pixel_owners(gbuffer: GBuffer, supersampling: int) -> torch.Tensor:
    """(N,) int64 index of the sub-sample whose light each sub-sample shares (itself for an owner).

    Args:
        gbuffer: N covered sub-samples of an (H, W) sub-sample image, H and W multiples of s.
        supersampling: s, sub-samples per pixel side.
    """
    height, width = gbuffer.image_size
    s = supersampling
    n = gbuffer.num_samples
    device = gbuffer.device
    row, column = gbuffer.pixel_index // width, gbuffer.pixel_index % width
    pixel = (row // s) * (width // s) + column // s
    slot = (row % s) * s + column % s
    # (pixels, s^2): the sub-sample in each slot of each pixel, -1 where uncovered.
    table = torch.full(((height // s) * (width // s), s * s), -1, dtype=torch.int64, device=device)
    table[pixel, slot] = torch.arange(n, device=device)
    owner = torch.arange(n, device=device)
    for later in range(1, s * s):
        here = table[:, later]
        for earlier in range(later):
            there = table[:, earlier]
            pairs = torch.nonzero((here >= 0) & (there >= 0)).squeeze(-1)
            i, j = here[pairs], there[pairs]
            joins = (owner[i] == i) & (owner[j] == j) & _same_surface(gbuffer, i, j)
            owner[i[joins]] = j[joins]
    return owner


def _same_surface(gbuffer: GBuffer, points: torch.Tensor, owners: torch.Tensor) -> torch.Tensor:
    """(K,) whether each of `points` may share the light of the matching one of `owners`."""
    normal = gbuffer.normal.index_select(0, owners)
    between = gbuffer.position.index_select(0, points) - gbuffer.position.index_select(0, owners)
    return (
        (gbuffer.object_id.index_select(0, points) == gbuffer.object_id.index_select(0, owners))
        & (gbuffer.material_id.index_select(0, points) == gbuffer.material_id.index_select(0, owners))
        & (dot(gbuffer.normal.index_select(0, points), normal) >= SHARED_NORMAL_COSINE)
        & (dot(between, normal).abs() <= MAX_PLANE_SLOPE * between.norm(dim=-1))
    )


class PixelGroups:
    """The groups of sub-samples that share their light, and where each group's light is evaluated.

    A group's light is evaluated at its centroid, with the mean of its shading normals: at its
    first sub-sample instead, every pixel's light would sit a quarter pixel up and left of where
    its sub-samples average it, a shift that shows as a bias where light changes fast across a
    pixel (Cornell box at 96x72, 4 filtered samples per group: 44.2 dB at the first sub-sample,
    46.4 at the centroid, 46.2 with a sample per sub-sample).

    Args:
        gbuffer: the shading points (N covered sub-samples).
        supersampling: s, sub-samples per pixel side.

    Attributes:
        owner: (N,) `pixel_owners`.
        owners: (R,) ascending indices of the owners, one per group.
        rank: (N,) the group of each sub-sample: the position of its owner in `owners`.
        gbuffer: the R groups as shading points: centroid positions, unit mean shading normals,
            the owner's other fields.
        primary: (R',) the groups that stand for their pixel on the pixel grid (`visibility`):
            each pixel's first.
        grid: the primary groups on the (H / s, W / s) pixel grid, for a `SurfaceFilter`.
    """

    def __init__(self, gbuffer: GBuffer, supersampling: int):
        self.owner = pixel_owners(gbuffer, supersampling)
        is_owner = self.owner == torch.arange(gbuffer.num_samples, device=gbuffer.device)
        self.owners = torch.nonzero(is_owner).squeeze(-1)
        self.rank = (torch.cumsum(is_owner, 0) - 1).index_select(0, self.owner)
        self.gbuffer = _group_gbuffer(gbuffer, self.owners, self.rank)
        height, width = gbuffer.image_size
        s = supersampling
        index = self.gbuffer.pixel_index
        pixel = (index // width // s) * (width // s) + index % width // s
        first = torch.full(((height // s) * (width // s),), gbuffer.num_samples, device=gbuffer.device)
        first.scatter_reduce_(0, pixel, self.owners, "amin")
        self.primary = torch.nonzero(first.index_select(0, pixel) == self.owners).squeeze(-1)
        self.grid = FilterGrid(
            (height // s, width // s),
            pixel.index_select(0, self.primary),
            self.gbuffer.position.index_select(0, self.primary),
            self.gbuffer.normal.index_select(0, self.primary),
        )

    def with_params(self, params: PreviewSurfaceParams) -> PixelGroups:
        """The same groups whose shading points take their owners' rows of `params` (other materials
        of the same sub-samples: a group is one material's, so it stays one)."""
        groups = copy.copy(self)
        groups.gbuffer = dataclasses.replace(self.gbuffer, params=params.index(self.owners))
        return groups

    def of(self, chunk: slice | torch.Tensor) -> tuple[slice | torch.Tensor, torch.Tensor]:
        """(groups, which) of the sub-samples of `chunk` (a slice of all of them, or P indices):
        the groups (a slice of them, or R' ascending indices) whose light they share and, per
        sub-sample, the position of its group among them (P,): values made for the groups expand
        to the chunk by `take_rows`.

        A slice takes the run of groups between its first and last (a group lies within one pixel,
        a row of sub-samples apart at most, so the run holds few others and no sort is needed);
        indices take exactly their groups."""
        if isinstance(chunk, slice):
            ranks = self.rank[chunk]
            if ranks.numel() == 0:
                return slice(0, 0), ranks
            first, last = int(ranks.min()), int(ranks.max())
            return slice(first, last + 1), ranks - first
        return torch.unique(self.rank.index_select(0, chunk), sorted=True, return_inverse=True)

    def visibility(self, sums: torch.Tensor, surface_filter: SurfaceFilter) -> torch.Tensor:
        """(N,) filtered visibility of per-point (N, 2) sums (sum w V, sum w) whose points share
        their owners' sums: filtered at the owners on the pixel grid (`grid`; `surface_filter` made
        over it, radius in pixels), where a quarter of the points at 2 x 2 sub-samples hold every
        distinct sum. An owner that is not its pixel's first (a second surface in a pixel: edges)
        takes its own ratio unfiltered, 1 where it has no sample."""
        held = sums.index_select(0, self.owners)
        weight = held[:, 1]
        visibility = torch.where(weight > 0, held[:, 0] / torch.where(weight > 0, weight, 1.0), 1.0)
        visibility.index_copy_(0, self.primary, surface_filter.visibility(held.index_select(0, self.primary)))
        return visibility.index_select(0, self.rank)


def _group_gbuffer(gbuffer: GBuffer, owners: torch.Tensor, rank: torch.Tensor) -> GBuffer:
    """The R groups of sub-samples (`rank` (N,) numbering them, `owners` (R,)) as shading points:
    centroids lifted onto a convex surface (`_convex_lift`), unit mean shading normals, the
    owners' other fields."""

    def mean(values: torch.Tensor) -> torch.Tensor:
        total = values.new_zeros(owners.shape[0], values.shape[1], dtype=torch.float32)
        return total.index_add_(0, rank, values.float())

    count = mean(torch.ones_like(gbuffer.depth).unsqueeze(-1))
    normal = torch.nn.functional.normalize(mean(gbuffer.normal), dim=-1)
    centroid = mean(gbuffer.position) / count
    position = centroid + normal * _convex_lift(gbuffer, rank, centroid, normal).unsqueeze(-1)
    fields = {
        f.name: getattr(gbuffer, f.name).index_select(0, owners)
        for f in dataclasses.fields(gbuffer)
        if f.name not in ("image_size", "params", "camera_position", "position", "normal")
    }
    return dataclasses.replace(
        gbuffer,
        position=position.to(gbuffer.position.dtype),
        normal=normal.to(gbuffer.normal.dtype),
        params=gbuffer.params.index(owners),
        **fields,
    )


def _convex_lift(gbuffer: GBuffer, rank: torch.Tensor, centroid: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """(R,) height (scene units) up each group's mean normal (R, 3) that puts its centroid (R, 3)
    on or above the tangent plane of every one of its sub-samples.

    The centroid of points on a convex surface lies inside it: by the sagitta R (1 - cos t) of a
    sphere of radius R whose normals turn by t across the group, or below the ridge where it spans a
    crease between flat facets. On a large, coarsely sampled sphere that is deeper than the shadow
    rays' offset, and the group shadows itself (acne). A convex surface lies below each of its
    tangent planes (the sub-samples' geometric normals'), so a point above all of them is outside
    it. A concave or flat group already lies on or in front of its surface and is not moved."""
    geometric = gbuffer.geometric_normal.float()
    below = dot(geometric, gbuffer.position.float() - centroid.index_select(0, rank))
    slope = dot(geometric, normal.index_select(0, rank)).clamp(min=MIN_LIFT_COSINE)
    lift = below.new_zeros(centroid.shape[0])
    return lift.scatter_reduce_(0, rank, (below / slope).clamp(min=0.0), "amax")


def take_rows(values: torch.Tensor, dim: int, index: torch.Tensor) -> torch.Tensor:
    """values.index_select(dim, index), one contiguous index_select per leading slab: on the CPU
    ~30x faster than index_select along a later axis of (F, S, P) factors (torch 2.13)."""
    if dim == 0:
        return values.index_select(0, index)
    lead, size = values.shape[:dim], values.shape[dim]
    slabs = values.reshape(math.prod(lead), size, *values.shape[dim + 1 :])
    out = values.new_empty(slabs.shape[0], index.shape[0], *values.shape[dim + 1 :])
    for k in range(slabs.shape[0]):
        torch.index_select(slabs[k], 0, index, out=out[k])
    return out.reshape(*lead, index.shape[0], *values.shape[dim + 1 :])
