"""An edge-aware box filter over a deep framebuffer's image, for the ratio estimator's shadows.

Heitz, Hill & McGuire 2018 filter the stochastic shadowed and unshadowed estimates with the same
filter and take their ratio: the visibility v = F(sum V cos / pdf) / F(sum cos / pdf) of each
shading point is then a weighted mean over its neighbours, which cuts the penumbrae's noise
while a fully lit (or fully shadowed) neighbourhood stays exactly 1 (or 0).

The filter is separable (a horizontal then a vertical pass of 2r + 1 taps) and averages only over
neighbours on the same surface as the centre: covered, normals within ~18 degrees, and lying
within ~3 degrees of the centre's tangent plane. Those weights depend on the G-buffer alone, so
they are made once, as one padded bool mask per axis and offset (4r bytes per sub-sample: as
float32 masks and per-tile copies they took 1.5 GB at 3840x2160 with r = 8); a filtering pass is
then 4r multiply-adds per channel and pixel.

`SurfaceFilter.visibility` filters only where it can change anything: a point whose (2r + 1)^2
window holds no shadowed sample (wV = w everywhere in it) gets exactly 1, and one whose window
holds no lit sample exactly 0, the values the whole filter gives there. Only the tiles of the image
near both (penumbrae, shadow edges, points the light does not reach) are filtered, each with its
halo of r; under a small light most of a large image is wholly lit or wholly shadowed.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from relight_torch.gbuffer import GBuffer, scatter_points

MIN_NORMAL_COSINE = 0.95
"""Neighbours whose shading normal is further from the centre's count as another surface."""
MAX_PLANE_SLOPE = 0.05
"""Neighbours further off the centre's tangent plane than this times their distance are another surface."""
TILE = 64
"""Side in sub-samples of the tiles `SurfaceFilter.visibility` filters or skips as a whole."""
MAX_TILE_FRACTION = 0.25
"""Above this share of tiles to filter, `SurfaceFilter.visibility` filters the whole image in one pass
instead (on the CPU the tiles' windows and weights cost more than the skipped tiles save)."""
TILE_BATCH = 64
"""Tiles filtered together: bounds the windows and weights a batch holds (~15 MB at r = 8)."""


@dataclass(frozen=True)
class FilterGrid:
    """The points a `SurfaceFilter` filters over when they are not a whole G-buffer's.

    Attributes:
        image_size: (H, W) of their image.
        pixel_index: (N,) int64 flat index of each point, distinct.
        position: (N, 3) world position.
        normal: (N, 3) unit shading normal.
    """

    image_size: tuple[int, int]
    pixel_index: torch.Tensor
    position: torch.Tensor
    normal: torch.Tensor

    @property
    def device(self) -> torch.device:
        return self.position.device

    def scatter(self, values: torch.Tensor) -> torch.Tensor:
        """Place per-point values (N, C) into the (H, W, C) image."""
        return scatter_points(self.image_size, self.pixel_index, values)


class SurfaceFilter:
    """Separable same-surface box filter of radius r over the G-buffer's (H, W) image.

    Args:
        gbuffer: the shading points (N covered sub-samples, `pixel_index` into H x W), or a
            `FilterGrid` of other points.
        radius: r >= 1, taps each side per pass.
    """

    def __init__(self, gbuffer: GBuffer | FilterGrid, radius: int):
        if radius < 1:
            raise ValueError(f"radius must be at least 1, got {radius}")
        self.gbuffer, self.radius = gbuffer, radius
        self.tile = max(TILE, radius)  # a window then reaches at most into the neighbouring tiles
        covered = gbuffer.scatter(torch.ones_like(gbuffer.position[:, :1]))[..., 0] > 0
        position, normal = gbuffer.scatter(gbuffer.position), gbuffer.scatter(gbuffer.normal)
        height, width = gbuffer.image_size
        rows, columns = -(-height // self.tile), -(-width // self.tile)
        # masks[axis]: (2r, R T + 2r, C T + 2r) bool, [k] true at the centre p of each same-surface
        # pair (p, p + offset k) along axis (0: y, 1: x), laid out as `_windows` pads the image, so
        # a tile's window of weights is a slice of it.
        self.masks = []
        for axis in (0, 1):
            size = (2 * radius, rows * self.tile + 2 * radius, columns * self.tile + 2 * radius)
            mask = torch.zeros(size, dtype=torch.bool, device=gbuffer.device)
            inside = mask.narrow(1, radius, height).narrow(2, radius, width)
            for k, offset in enumerate(self.offsets):
                pairs = self._same_surface(covered, position, normal, axis, offset)
                inside[k].narrow(axis, max(0, -offset), inside.shape[axis + 1] - abs(offset)).copy_(pairs)
            self.masks.append(mask)

    @property
    def offsets(self) -> list[int]:
        return [d for d in range(-self.radius, self.radius + 1) if d != 0]

    @staticmethod
    def _pair(image: torch.Tensor, axis: int, offset: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(centre, neighbour) views of `image` over the pixels whose neighbour at `offset` along
        `axis` lies inside the image."""
        size = image.shape[axis]
        centre = image.narrow(axis, max(0, -offset), size - abs(offset))
        return centre, image.narrow(axis, max(0, offset), size - abs(offset))

    def _same_surface(self, covered, position, normal, axis: int, offset: int) -> torch.Tensor:
        both = self._pair(covered, axis, offset)
        p, q = self._pair(position, axis, offset)
        n, m = self._pair(normal, axis, offset)
        between = q - p
        plane = (between * n).sum(-1).abs()
        same = (
            both[0]
            & both[1]
            & ((n * m).sum(-1) >= MIN_NORMAL_COSINE)
            & (plane <= MAX_PLANE_SLOPE * between.norm(dim=-1))
        )
        return same

    def weight(self, axis: int, k: int) -> torch.Tensor:
        """(H', W') bool view: the pairs (p, p + offset k) along `axis` over the centres of `_pair`."""
        height, width = self.gbuffer.image_size
        offset, r = self.offsets[k], self.radius
        inside = self.masks[axis][k].narrow(0, r, height).narrow(1, r, width)
        return inside.narrow(axis, max(0, -offset), inside.shape[axis] - abs(offset))

    def __call__(self, values: torch.Tensor) -> torch.Tensor:
        """(N, C) per-point values filtered: sum over same-surface neighbours (the centre included)
        of a horizontal, then a vertical box of 2r + 1 taps. Sums, not means: filter a numerator
        and a denominator and divide.

        The passes run on (C, H, W) planes: each tap is one multiply-add of contiguous rows with
        the (H', W') weights broadcast over C (a trailing C of 2 defeats the CPU's vector loops).
        In and out by `index_copy_` / `index_select` (on the CPU 1.5-4x faster than indexing).
        """
        height, width = self.gbuffer.image_size
        planes = values.new_zeros(values.shape[-1], height * width)
        planes.index_copy_(1, self.gbuffer.pixel_index, values.t())
        image = planes.reshape(-1, height, width)
        for axis in (1, 0):
            total = image.clone()
            for k, offset in enumerate(self.offsets):
                centre, _ = self._pair(total, axis + 1, offset)
                _, neighbour = self._pair(image, axis + 1, offset)
                centre.addcmul_(neighbour, self.weight(axis, k).to(values.dtype))
            image = total
        return image.reshape(values.shape[-1], -1).index_select(1, self.gbuffer.pixel_index).t()

    def visibility(self, sums: torch.Tensor) -> torch.Tensor:
        """(N,) filtered visibility F(sum w V) / F(sum w) of per-point (N, 2) sums (sum w V, sum w),
        0 where F(sum w) is 0, computed only in the tiles where it is not a constant 1 or 0 (module
        doc): the numbers of filtering the whole image with `__call__` at every point with a
        sample of its own (sum w > 0). A point without one, whose window holds none either, gets
        1 instead of 0 in a tile left unfiltered (no shadowed sample near it): the ratio
        estimator's points whose samples all fell below their horizon then keep their
        unshadowed closed form.
        """
        height, width = self.gbuffer.image_size
        tile = self.tile
        planes = sums.new_zeros(2, height * width)
        planes.index_copy_(1, self.gbuffer.pixel_index, sums.t())
        planes = planes.reshape(2, height, width)
        shadowed, unshadowed = planes
        # Dark: a shadowed sample; lit: a sample the light reaches unshadowed.
        dark, lit = shadowed < unshadowed, shadowed > 0
        rows, columns = -(-height // tile), -(-width // tile)
        flags = torch.stack((dark, lit)).to(sums.dtype)
        flags = torch.nn.functional.pad(flags, (0, columns * tile - width, 0, rows * tile - height))
        per_tile = torch.nn.functional.max_pool2d(flags.unsqueeze(0), tile)  # (1, 2, rows, columns)
        near = torch.nn.functional.max_pool2d(per_tile, 3, stride=1, padding=1)[0] > 0
        result = near[1].to(sums.dtype).repeat_interleave(tile, 0).repeat_interleave(tile, 1)[:height, :width]
        result = result.contiguous()
        needed = torch.nonzero((near[0] & near[1]).flatten()).squeeze(-1)
        if needed.numel() > MAX_TILE_FRACTION * rows * columns:  # shadows everywhere: one pass over the image
            filtered = self(sums)
            return torch.where(
                filtered[:, 1] > 0, filtered[:, 0] / torch.where(filtered[:, 1] > 0, filtered[:, 1], 1.0), 0.0
            )
        if needed.numel():
            padded = result.new_zeros(rows * tile, columns * tile)
            padded[:height, :width] = result
            view = padded.reshape(rows, tile, columns, tile).permute(0, 2, 1, 3).reshape(rows * columns, tile, tile)
            r = self.radius
            around = torch.nn.functional.pad(planes, (r, columns * tile - width + r, r, rows * tile - height + r))
            for batch in needed.split(TILE_BATCH):
                filtered = self._filter_tiles(around, batch, columns)  # (B, 2, T, T)
                ratio = torch.where(
                    filtered[:, 1] > 0, filtered[:, 0] / torch.where(filtered[:, 1] > 0, filtered[:, 1], 1.0), 0.0
                )
                view.index_copy_(0, batch, ratio)
            result = view.reshape(rows, columns, tile, tile).permute(0, 2, 1, 3).reshape(rows * tile, -1)
            result = result[:height, :width]
        return result.reshape(-1).index_select(0, self.gbuffer.pixel_index)

    def _filter_tiles(self, around: torch.Tensor, needed: torch.Tensor, columns: int) -> torch.Tensor:
        """(B, C, T, T) the separable filter's sums over the B tiles `needed` (flat tile indices,
        `columns` tiles a row) of (C, H, W) planes zero-padded to (C, R T + 2r, C T + 2r) (a halo
        of r around the tile grid): each tile's window with its halo, the taps of `__call__` in
        the same order."""
        r, tile = self.radius, self.tile
        size = tile + 2 * r
        image = self._windows(around, needed, columns)  # (B, C, size, size)
        for axis in (1, 0):
            chosen = self._windows(self.masks[axis], needed, columns).to(around.dtype)  # (B, 2r, size, size)
            total = image.clone()
            for k, offset in enumerate(self.offsets):
                dim = axis + 2
                centre = total.narrow(dim, max(0, -offset), size - abs(offset))
                neighbour = image.narrow(dim, max(0, offset), size - abs(offset))
                weight = chosen[:, k : k + 1].narrow(dim, max(0, -offset), size - abs(offset))
                centre.addcmul_(neighbour, weight)
            image = total
        return image[:, :, r : r + tile, r : r + tile]

    def _windows(self, padded: torch.Tensor, needed: torch.Tensor, columns: int) -> torch.Tensor:
        """(B, C, T + 2r, T + 2r) windows of padded (C, R T + 2r, C T + 2r) planes around the tiles `needed`."""
        size, tile = self.tile + 2 * self.radius, self.tile
        starts = [(int(i) // columns * tile, int(i) % columns * tile) for i in needed.tolist()]
        return torch.stack([padded[:, y : y + size, x : x + size] for y, x in starts])
