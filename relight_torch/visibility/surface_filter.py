"""An edge-aware box filter over a deep framebuffer's image, for the ratio estimator's shadows.

Heitz, Hill & McGuire 2018 filter the stochastic shadowed and unshadowed estimates with the same
filter and take their ratio: the visibility v = F(sum V cos / pdf) / F(sum cos / pdf) of each
shading point is then a weighted mean over its neighbours, which cuts the penumbrae's noise
while a fully lit (or fully shadowed) neighbourhood stays exactly 1 (or 0).

The filter is separable (a horizontal then a vertical pass of 2r + 1 taps) and averages only over
neighbours on the same surface as the centre: covered, normals within ~18 degrees, and lying
within ~3 degrees of the centre's tangent plane. Those weights depend on the G-buffer alone, so
they are made once; a filtering pass is then 4r multiply-adds per channel and pixel.
"""

from __future__ import annotations

import torch

from relight_torch.gbuffer import GBuffer

MIN_NORMAL_COSINE = 0.95
"""Neighbours whose shading normal is further from the centre's count as another surface."""
MAX_PLANE_SLOPE = 0.05
"""Neighbours further off the centre's tangent plane than this times their distance are another surface."""


class SurfaceFilter:
    """Separable same-surface box filter of radius r over the G-buffer's (H, W) image.

    Args:
        gbuffer: the shading points (N covered sub-samples, `pixel_index` into H x W).
        radius: r >= 1, taps each side per pass.
    """

    def __init__(self, gbuffer: GBuffer, radius: int):
        if radius < 1:
            raise ValueError(f"radius must be at least 1, got {radius}")
        self.gbuffer, self.radius = gbuffer, radius
        covered = gbuffer.scatter(torch.ones_like(gbuffer.position[:, :1]))[..., 0] > 0
        position, normal = gbuffer.scatter(gbuffer.position), gbuffer.scatter(gbuffer.normal)
        # weights[axis][k]: (H', W') float mask of the pairs (p, p + offset k) along axis (1: x, 0: y).
        self.weights = [
            [self._same_surface(covered, position, normal, axis, offset) for offset in self.offsets] for axis in (0, 1)
        ]

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
        return same.to(position.dtype)

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
            for offset, weight in zip(self.offsets, self.weights[axis], strict=True):
                centre, _ = self._pair(total, axis + 1, offset)
                _, neighbour = self._pair(image, axis + 1, offset)
                centre.addcmul_(neighbour, weight)
            image = total
        return image.reshape(values.shape[-1], -1).index_select(1, self.gbuffer.pixel_index).t()
