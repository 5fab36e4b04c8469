"""The points a light's transport is evaluated at: every shading point, or the pixel groups that
share their light (`direct.sharing`), each with its fixed light samples and its view terms."""

from __future__ import annotations

import copy
import dataclasses
from typing import NamedTuple

import torch

from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.direct.sharing import PixelGroups
from relight_torch.gbuffer import GBuffer
from relight_torch.light_samples import fixed_light_samples
from relight_torch.math.frame import dot


def take(values: torch.Tensor, rows: slice | torch.Tensor) -> torch.Tensor:
    """values[rows] along the first axis: a slice as a view, indices through `index_select` (the
    advanced index `values[rows]` of a few thousand rows of a million-row tensor ran ~100x slower
    on the CPU: ~7 ms against 0.03 ms, torch 2.13)."""
    return values[rows] if isinstance(rows, slice) else values.index_select(0, rows)


class Points(NamedTuple):
    """Where a transport is evaluated: the points of `gbuffer`, their fixed light samples (N, S, 2),
    their `viewer_of` terms, and the pixel groups they stand for (None: the shading points themselves)."""

    gbuffer: GBuffer
    samples: torch.Tensor
    viewer: tuple[torch.Tensor, torch.Tensor, torch.Tensor]
    groups: PixelGroups | None = None


def viewer_of(g: GBuffer) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(N, 3) unit directions E from the points of `g` to the camera, (N,) N.E and (N,) 1 / |N| of
    their shading normals N (`EvaluationPoints.view_directions`)."""
    wo, normal = g.wo_world(), g.normal
    inverse_norm = dot(normal, normal).rsqrt_()
    return wo, dot(wo, normal).mul_(inverse_norm), inverse_norm


class EvaluationPoints:
    """The `Points` of a G-buffer's shading points and of their pixel groups, made on first use and kept.

    Args:
        gbuffer: the shading points.
        seed: seed of their fixed light samples (`light_samples.fixed_light_samples`).
        groups: the sub-samples that share their light, or None.
    """

    def __init__(self, gbuffer: GBuffer, seed: int, groups: PixelGroups | None):
        self.gbuffer = gbuffer
        self.seed = seed
        self.groups = groups
        self._u: dict[int, torch.Tensor] = {}
        # (wo, N.E / |N|, 1 / |N|) of every point, made on first use (`view_directions`).
        self._viewer: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
        self._group_points: dict[int, Points] = {}  # the groups as shading points, by samples per point

    def with_params(self, params: PreviewSurfaceParams) -> EvaluationPoints:
        """These points with other materials (rows as the G-buffer's): the fixed samples and the
        view terms kept (geometry), the pixel groups given their owners' new materials."""
        points = copy.copy(self)
        points.gbuffer = dataclasses.replace(self.gbuffer, params=params)
        points.groups = None if self.groups is None else self.groups.with_params(params)
        points._group_points = {}
        return points

    def fixed_samples(self, num_samples: int) -> torch.Tensor:
        """(N, S, 2) the fixed light-sample numbers of every point for S samples, made once per S."""
        if num_samples not in self._u:
            g = self.gbuffer
            self._u[num_samples] = fixed_light_samples(
                g.num_samples, num_samples, self.seed, g.device, g.position.dtype
            )
        return self._u[num_samples]

    def view_directions(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(N, 3) unit world directions E to the viewer, (N,) N.E and (N,) 1 / |N| of the shading
        normals N (stored in half precision: |N| = 1 to ~5e-4), made on first use: a Relighter
        handed its unit images (the multiview relighter's) never reads them.

        The BRDF takes N.E and N.L of the unit normal: with E, L and N unit in one space, N.h
        never exceeds |h|, which a sharp lobe's peak would otherwise see."""
        if self._viewer is None:
            self._viewer = viewer_of(self.gbuffer)
        return self._viewer

    def at(self, num_samples: int, shared: bool) -> Points:
        """The points a sample group's transport is evaluated at (`tracing.chunk_transport`),
        `num_samples` fixed light samples each: every shading point, or with `shared` the pixel
        groups (their owners' samples), made once."""
        u = self.fixed_samples(num_samples)
        if not shared:
            return Points(self.gbuffer, u, self.view_directions())
        groups = self.groups
        assert groups is not None, "shared transports come with pixel groups"
        if num_samples not in self._group_points:
            owned = u.index_select(0, groups.owners)
            self._group_points[num_samples] = Points(groups.gbuffer, owned, viewer_of(groups.gbuffer), groups)
        return self._group_points[num_samples]
