"""The ratio estimator's filtered visibility F(sum w V) / F(sum w) (Heitz et al. 2018): a light's
per-point shadowed and unshadowed sample sums filtered over the same surface
(`visibility.surface_filter`), on the sub-samples or on the pixel grid of the groups that share
their light (`direct.sharing`), and folded into its transports' diffuse ratios."""

from __future__ import annotations

import torch

from relight_torch.direct.points import take
from relight_torch.direct.sharing import PixelGroups
from relight_torch.direct.transport import Transport
from relight_torch.gbuffer import GBuffer
from relight_torch.visibility.surface_filter import SurfaceFilter


class VisibilityFilter:
    """The filtered visibility of a G-buffer's shading points, the filter's weights made once.

    Args:
        gbuffer: the shading points.
        radius: the filter's radius in sub-samples (> 0).
        supersampling: s, sub-samples per pixel side.
        groups: the sub-samples that share their light (filtered on their pixel grid), or None.
    """

    def __init__(self, gbuffer: GBuffer, radius: int, supersampling: int, groups: PixelGroups | None):
        self.gbuffer = gbuffer
        self.radius = radius
        self.supersampling = supersampling
        self.groups = groups
        self._surface_filter: SurfaceFilter | None = None

    def visibility(self, sums: torch.Tensor) -> torch.Tensor:
        """(N,) filtered visibility F(sum w V) / F(sum w) of per-point (N, 2) sums (0 where unlit),
        filtered only near shadows (`SurfaceFilter.visibility`): the filter's weights are made once,
        and a moved light pays only for the tiles its shadows' edges cross."""
        if self.groups is None:
            if self._surface_filter is None:
                self._surface_filter = SurfaceFilter(self.gbuffer, self.radius)
            return self._surface_filter.visibility(sums)
        if self._surface_filter is None:  # on the pixel grid: the radius in pixels
            radius = max(1, self.radius // self.supersampling)
            self._surface_filter = SurfaceFilter(self.groups.grid, radius)
        return self.groups.visibility(sums, self._surface_filter)

    def fold(self, transports: list[Transport], visibility: torch.Tensor | None = None) -> None:
        """Fold the filtered visibility into the transports' diffuse ratios and drop their sums.
        The groups' sums are filtered together: each sum is already its group's mean over its
        samples. A `visibility` (N,) already filtered from the same sums is used as it is."""
        if visibility is None:
            g = self.gbuffer
            sums = g.position.new_zeros(g.num_samples, 2)
            for transport in transports:
                assert transport.shadow_sums is not None, "every transport of a filtered light keeps its sums"
                if transport.points is None:
                    sums += transport.shadow_sums
                else:  # the groups' points are disjoint (see `LightStages.images`)
                    sums.index_copy_(0, transport.points, transport.shadow_sums)
            visibility = self.visibility(sums)
        for transport in transports:
            points = transport.points
            assert transport.diffuse_ratio is not None, "a filtered light has a closed form, hence ratios"
            transport.diffuse_ratio = transport.diffuse_ratio * (
                visibility if points is None else take(visibility, points)
            )
            transport.shadow_sums = None
