"""A light's first two stages on one G-buffer: its transport (light samples, shadow rays, BRDF
factors, `tracing`) and its unit images (the transport times the light's shaping, summed per
point), made whole, tile by tile without keeping the transport, or at some points only."""

from __future__ import annotations

import collections
import copy
import dataclasses
import functools

import numpy as np
import torch

from relight_torch.brdf import preview_surface
from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.direct.images import unit_light
from relight_torch.direct.points import EvaluationPoints, Points, take
from relight_torch.direct.rig import LightState
from relight_torch.direct.settings import RelightSettings
from relight_torch.direct.sharing import PixelGroups, take_rows
from relight_torch.direct.tracing import (
    chunk_transport,
    chunks,
    filters_visibility,
    joined,
    kept_transport,
    scalar_radiance,
)
from relight_torch.direct.transport import Transport
from relight_torch.direct.visibility_filter import VisibilityFilter
from relight_torch.gbuffer import GBuffer
from relight_torch.light_samples import adaptive_sample_count, angular_radius
from relight_torch.lights.emission import is_delta_light
from relight_torch.lights.light import Light, LightKind
from relight_torch.lights.shaping import emission_factor
from relight_torch.material_edits import FACTOR_COLOUR_INPUTS, MaterialChange
from relight_torch.parallel import parallel_map, tile_threads
from relight_torch.visibility import Visibility
from relight_torch.visibility.rays import RayVisibility

# A sample group: (its points, None for all; samples per point; whether the pixel groups share them).
SampleGroup = tuple[torch.Tensor | None, int, bool]


class LightStages:
    """Transports and unit images of lights on one G-buffer.

    Args:
        gbuffer: the covered sub-samples (device and dtype of every computation).
        visibility: shadow queries.
        settings: sampling settings.
        filter_radius: the visibility filter's radius in sub-samples (0: none).
        supersampling: s, sub-samples per pixel side.
        counters: 'visibility' and 'shading' passes are counted here (`Relighter.counters`).
    """

    def __init__(
        self,
        gbuffer: GBuffer,
        visibility: Visibility,
        settings: RelightSettings,
        filter_radius: int,
        supersampling: int,
        counters: collections.Counter[str],
    ):
        self.visibility = visibility
        self.settings = settings
        self.filter_radius = filter_radius
        self.counters = counters
        self._material_terms(gbuffer)
        # The sub-samples that share their light (`direct.sharing`), or None.
        sharing = settings.shared_lighting and supersampling > 1 and filter_radius > 0
        groups = PixelGroups(gbuffer, supersampling) if sharing else None
        self._groups = groups
        self.points = EvaluationPoints(gbuffer, settings.seed, groups)
        self.filter = VisibilityFilter(gbuffer, filter_radius, supersampling, groups)

    def _material_terms(self, gbuffer: GBuffer) -> None:
        """Take `gbuffer` and what its materials decide: the clearcoat factors, the glossy points."""
        self.gbuffer = gbuffer
        # Whether the transport factors carry the clearcoat lobe: one answer for every chunk.
        self._coat = bool(gbuffer.params.clearcoat.any())
        # The glossy and the matte points, or None for both when the image is all one kind.
        glossy = preview_surface.glossy(gbuffer.params)
        self._all_glossy = bool(glossy.all())
        self._glossy_split = None
        if glossy.any() and not self._all_glossy:
            self._glossy_split = (torch.nonzero(~glossy).squeeze(-1), torch.nonzero(glossy).squeeze(-1))
        self._factor_colours: torch.Tensor | None = None  # (F, N, 3), made on first use
        self._stale_colours: torch.Tensor | None = None  # (N,) bool: its rows to make again, or None

    def with_params(self, params: PreviewSurfaceParams, change: MaterialChange) -> LightStages:
        """These stages for other materials of the same points: the points' geometry, pixel groups,
        fixed samples and visibility filter kept, the rest made for `params` (rows as the G-buffer's),
        which differ from the current ones by `change`. The factor colours made so far are updated in
        place at the changed rows, where a changed input enters them: these stages are not to be
        used again."""
        stages = copy.copy(self)
        stages._material_terms(dataclasses.replace(self.gbuffer, params=params))
        stages.points = self.points.with_params(params)
        if self._factor_colours is not None and stages._coat == self._coat:
            stages._factor_colours = self._factor_colours
            stages._stale_colours = self._stale_colours
            if change.inputs & FACTOR_COLOUR_INPUTS:  # made again as points are shaded (`_colours_at`)
                stale = self._stale_colours
                stages._stale_colours = change.rows.clone() if stale is None else stale | change.rows
        return stages

    def same_sample_groups(self, other: LightStages) -> bool:
        """Whether `other` (of the same points, other materials) samples and factors every light
        as these do: the same glossy points and the same clearcoat factors, so that transports
        made by either serve both."""
        if (self._coat, self._all_glossy) != (other._coat, other._all_glossy):
            return False
        if self._glossy_split is None or other._glossy_split is None:
            return self._glossy_split is None and other._glossy_split is None
        return all(torch.equal(a, b) for a, b in zip(self._glossy_split, other._glossy_split, strict=True))

    # -- sampling ---------------------------------------------------------------------------------

    def num_light_samples(self, light: Light) -> int:
        """Light samples per point the light gets without a visibility filter (`RelightSettings`)."""
        settings = self.settings
        if is_delta_light(light):
            return 1
        if light.kind is LightKind.DOME:
            return settings.dome_samples
        if settings.full_sampling_angle <= 0.0:  # every light takes them all: no pass over the points
            return settings.area_samples
        return adaptive_sample_count(
            settings.area_samples,
            settings.min_area_samples,
            angular_radius(light, self.gbuffer.position),
            np.radians(settings.full_sampling_angle),
        )

    def sample_groups(self, light: Light) -> list[SampleGroup]:
        """(points or None for all, samples per point, shared) of each group the light's
        transport is made in: a light whose visibility is filtered takes `filtered_area_samples`
        at matte points, evaluated once per pixel group where `RelightSettings.shared_lighting`
        (shared), and its usual count at glossy ones (`RelightSettings.filtered_area_samples`)."""
        samples = self.num_light_samples(light)
        if self._all_glossy or not filters_visibility(light, self.filter_radius):
            return [(None, samples, False)]
        few, shared = self.settings.filtered_area_samples, self._groups is not None and scalar_radiance(light)
        if self._glossy_split is None:
            return [(None, few, shared)]
        matte, glossy = self._glossy_split
        return [(matte, few, shared), (glossy, samples, False)]

    def transport_light(self, light: Light) -> Light:
        """The unshaped unit light whose transport is cached (shaping and colour apply later)."""
        light = dataclasses.replace(unit_light(light), shaping=None, barzel=None)
        if light.shadow_link is not None and not isinstance(self.visibility, RayVisibility):
            raise ValueError(f"{light.path}: shadow linking needs Embree shadow rays (shadows='embree')")
        return light

    def transport_bytes(self, light: Light) -> int:
        """Bytes of the light's whole transport, kept, estimated from the kept layout (`Transport`):
        per point and sample up to six scalar factors and a direction, or two RGB lobes and a
        direction, in the G-buffer's dtype. Grouped as `transports` groups it: by the unit light."""
        size = self.gbuffer.position.element_size()
        per_sample = (6 + 3) * size if light.texture is None else (2 * 3 + 3) * size
        samples = max(num for _, num, _ in self.sample_groups(self.transport_light(light)))
        return self.gbuffer.num_samples * samples * per_sample

    # -- transports -------------------------------------------------------------------------------

    def transports(self, light: Light) -> list[Transport]:
        """Light samples, shadow rays and BRDF of the light made unshaped unit light
        (`transport_light`) at the points it reaches, one transport per sample group
        (`sample_groups`), its visibility filtered."""
        light = self.transport_light(light)
        transports = []
        # Tiles of points on threads of their own on the CPU (`relight_torch.parallel`).
        threads = tile_threads(self.gbuffer.device, self.visibility.thread_safe)
        for points, num_samples, shared in self.sample_groups(light):
            tiles = chunks(self.gbuffer.num_samples, self.settings.chunk_samples, num_samples, points, threads)
            # Made here, shared by the tiles.
            shade = functools.partial(self._chunk_transport, light, points=self.points.at(num_samples, shared))
            parts = parallel_map(shade, tiles, threads)
            transports.append(parts[0] if len(parts) == 1 else self._joined(parts, tiles))
        if transports[0].shadow_sums is not None:
            self.filter.fold(transports)
        self.counters["visibility"] += 1
        return transports

    def retrace_stale(self, state: LightState, points: torch.Tensor | None = None) -> None:
        """Trace the light of `state` again at its stale points (`LightState.stale`) among `points`
        ((M,) ascending; None: all), before its kept transport shades them (`retrace_at`)."""
        if state.stale is None or state.transports is None:
            return
        todo = _take_marked(state.stale, points)
        if todo.numel():
            self.retrace_at(state.light, state.transports, todo)
        if points is None:
            state.stale = None

    def retrace_at(self, light: Light, transports: list[Transport], todo: torch.Tensor) -> None:
        """Trace the light again at the shading points `todo` ((K,) ascending) for the current
        materials and write their BRDF values into its kept `transports` (one per sample group), in place:
        what a material edit of those points changes. The rest of a transport does not depend on the
        materials (the samples, their directions, the points reached, the ratio estimator's factors
        and the filtered visibility), except for a dome, whose BRDF samples follow them: its ratios
        are taken too."""
        unit = self.transport_light(light)
        g = self.gbuffer
        threads = tile_threads(g.device, self.visibility.thread_safe)
        for (points, num_samples, shared), transport in zip(self.sample_groups(unit), transports, strict=True):
            among = self._among(points, todo)
            if among.numel() == 0:
                continue
            tiles = chunks(g.num_samples, self.settings.chunk_samples, num_samples, among, threads)
            shade = functools.partial(self._chunk_transport, unit, points=self.points.at(num_samples, shared))
            for part, tile in zip(parallel_map(shade, tiles, threads), tiles, strict=True):
                assert isinstance(tile, torch.Tensor), "tiles of a list of points are lists of points"
                _write_part(transport, part, tile)

    def _among(self, group: torch.Tensor | None, todo: torch.Tensor) -> torch.Tensor:
        """The points of a sample group (`sample_groups`: (P,) or None for all) among the shading
        points `todo` ((K,) ascending)."""
        if group is None:
            return todo
        member = torch.zeros(self.gbuffer.num_samples, dtype=torch.bool, device=todo.device)
        member[group] = True
        return todo[member[todo]]

    def kept_transport(self, group: list[tuple[torch.Tensor, Transport]]) -> Transport:
        """One sample group's transport from the parts traced for its points (`tracing.kept_transport`)."""
        return kept_transport(group, self.gbuffer.num_samples, self.gbuffer.device)

    def _joined(self, parts: list[Transport], tiles: list[slice | torch.Tensor]) -> Transport:
        return joined(parts, tiles, self.gbuffer.num_samples, self.gbuffer.device)

    def _chunk_transport(self, light: Light, chunk: slice | torch.Tensor, points: Points) -> Transport:
        return chunk_transport(light, chunk, points, self.visibility, self.filter_radius, self._coat)

    # -- unit images ------------------------------------------------------------------------------

    def images(self, light: Light, transports: list[Transport]) -> torch.Tensor:
        """The light's diffuse and specular unit images (2, N, 3) from its `transports`: each
        transport times the light's shaping, per point."""
        if len(transports) == 1 and transports[0].points is None:
            images = self.per_point(light, transports[0])
        else:  # groups of points: disjoint, so their sums land side by side
            images = self.gbuffer.position.new_zeros(2, self.gbuffer.num_samples, 3)
            for transport in transports:
                per_point = self.per_point(light, transport)
                if transport.points is None:
                    images += per_point
                else:  # copied, not added: 7 ms against 36 ms for 543,000 of 613,120 points
                    images.index_copy_(1, transport.points, per_point)
        self.counters["shading"] += 1
        return images

    def streamed_images(self, light: Light) -> torch.Tensor:
        """The light's unit images (2, N, 3) made tile by tile, each tile's transport dropped once
        shaded: what a light costs when its transport does not fit the budget (a later shaping
        edit traces it again). The same numbers as `transports` then `images`."""
        g = self.gbuffer
        images = g.position.new_zeros(2, g.num_samples, 3)
        sums = self.traced_images(light, None, images, None)
        if sums is not None:  # the filtered visibility multiplies the diffuse image (see VisibilityFilter.fold)
            images[0].mul_(self.filter.visibility(sums).unsqueeze(-1))
        self.counters["visibility"] += 1
        self.counters["shading"] += 1
        return images

    def traced_images(
        self,
        light: Light,
        todo: torch.Tensor | None,
        images: torch.Tensor,
        sums: torch.Tensor | None,
        parts: list[list[tuple[torch.Tensor, Transport]]] | None = None,
    ) -> torch.Tensor | None:
        """Add the light's unit images at the shading points `todo` ((K,) ascending; None: all) to
        `images` (2, N, 3), traced tile by tile; the per-point sums of a filtered visibility go to
        `sums` ((N, 2), made on first need), which is returned. The filtered visibility itself is
        not applied (it needs every point's sums). Each tile's transport is dropped once shaded,
        or with `parts` (one list per sample group) appended to its group's list with its points."""
        unit = self.transport_light(light)
        g = self.gbuffer
        threads = tile_threads(g.device, self.visibility.thread_safe)
        for group, (points, num_samples, shared) in enumerate(self.sample_groups(unit)):
            if todo is not None:
                points = self._among(points, todo)
                if points.numel() == 0:
                    continue
            tiles = chunks(g.num_samples, self.settings.chunk_samples, num_samples, points, threads)
            shading = self.points.at(num_samples, shared)

            def tile(
                chunk: slice | torch.Tensor,
                shading: Points = shading,
            ) -> tuple[torch.Tensor, torch.Tensor, Transport]:
                part = self._chunk_transport(unit, chunk, shading)
                if part.points is None:  # the whole tile: name its points, as `joined` does
                    part.points = (
                        torch.arange(chunk.start, chunk.stop, device=g.device) if isinstance(chunk, slice) else chunk
                    )
                return part.points, self.per_point(light, part), part

            for (index, per_point, part), chunk in zip(parallel_map(tile, tiles, threads), tiles, strict=True):
                images.index_add_(1, index, per_point)
                shadow_sums = part.shadow_sums
                if parts is not None:
                    assert isinstance(chunk, torch.Tensor), "parts are kept of point lists (progressive refinement)"
                    parts[group].append((chunk, part))
                if shadow_sums is not None:
                    sums = g.position.new_zeros(g.num_samples, 2) if sums is None else sums
                    sums.index_add_(0, index, shadow_sums)
        return sums

    def per_point(self, light: Light, transport: Transport) -> torch.Tensor:
        """(2, P, 3) diffuse and specular sums of one transport's samples at its points, shaped."""
        factor = self._emission_factor(light, transport)
        if transport.factors is not None:
            per_point = self._combined(transport, factor)
        else:
            assert transport.lobes is not None, "a transport keeps either scalar factors or lobes"
            lobes = transport.lobes if factor is None else transport.lobes * factor
            per_point = lobes[:, 0] if lobes.shape[1] == 1 else lobes.sum(1)
            if transport.diffuse_ratio is not None and lobes.shape[1] == 1:
                per_point = per_point.clone()  # never scale the cache
        if transport.diffuse_ratio is not None:
            per_point[0].mul_(transport.diffuse_ratio.unsqueeze(-1))
        return per_point

    def _combined(self, transport: Transport, factor: torch.Tensor | None) -> torch.Tensor:
        """(2, P, 3) diffuse and specular sums of a transport kept as scalar factors, each sample
        times its shaping `factor` (S, P, 3) when given."""
        factors = transport.factors
        assert factors is not None and transport.colour is not None, "a factor transport has both"
        if factor is None:  # scalar sums (F, P, 1): the light's colour multiplies the result
            sums = (factors[:, 0] if factors.shape[1] == 1 else factors.sum(1)).unsqueeze(-1)
        else:  # one sample at a time: (F, P, 3) slabs, never an (F, S, P, 3) temporary
            sums = factors[:, 0].unsqueeze(-1) * factor[0]
            for s in range(1, factors.shape[1]):
                sums.addcmul_(factors[:, s].unsqueeze(-1), factor[s])
        colours = self._colours_at(transport.points)
        return torch.stack(preview_surface.combine_factors(colours, sums)).mul_(transport.colour)

    def _colours_at(self, points: torch.Tensor | None) -> torch.Tensor:
        """(F, P, 3) `preview_surface.factor_colours` at the shading points `points` ((P,); None:
        all), made on first use; the rows a material edit changed are made again when first read."""
        if self._factor_colours is None:
            self._factor_colours = preview_surface.factor_colours(self.gbuffer.params, self._coat)
        if self._stale_colours is not None:
            todo = _take_marked(self._stale_colours, points)
            if todo.numel():
                made = preview_surface.factor_colours(self.gbuffer.params.index(todo), self._coat)
                self._factor_colours.index_copy_(1, todo, made)
            if points is None:
                self._stale_colours = None
        colours = self._factor_colours
        return colours if points is None else colours.index_select(1, points)

    def _emission_factor(self, light: Light, transport: Transport) -> torch.Tensor | None:
        """(S, P, 3) ShapingAPI x Barzel factor of each cached sample; None when nothing applies."""
        if not transport.shapeable or (light.shaping is None and light.barzel is None):
            return None
        position = self.gbuffer.position
        if light.barzel is not None and transport.points is not None:  # receivers matter to Barzel only
            position = take(position, transport.points)
        origin = torch.as_tensor(light.world_from_light[:3, 3], device=position.device, dtype=position.dtype)
        return emission_factor(light, transport.emission_in(light), position, origin)


def _take_marked(marked: torch.Tensor, points: torch.Tensor | None) -> torch.Tensor:
    """The points marked in `marked` ((N,) bool) among `points` ((M,) ascending; None: all), which
    are unmarked: (K,) ascending, for the caller to make again."""
    todo = torch.nonzero(marked).squeeze(-1) if points is None else points[take(marked, points)]
    marked.index_fill_(0, todo, False)
    return todo


def _write_part(transport: Transport, part: Transport, chunk: torch.Tensor) -> None:
    """Write into `transport` the BRDF values (factors or lobes; a dome's ratios) of `part`, traced
    at the shading points `chunk` ((K,) ascending): at each of them `transport` holds, `part`'s
    values, or zero where `part` dropped the point (no sample lights it)."""
    if transport.points is None:
        where, points = chunk, chunk
    else:
        where, held = transport.locate(chunk)
        where, points = where[held], chunk[held]
    assert part.points is not None, "a transport of a list of points names them"
    source, found = part.locate(points)
    fields = [("factors", 2), ("lobes", 2)]
    if part.shadow_sums is None:  # a filtered light's part lacks the filtered visibility its ratios carry
        fields.append(("diffuse_ratio", 0))
    for name, dim in fields:
        values, new = getattr(transport, name), getattr(part, name)
        if values is None:
            continue
        assert new is not None, f"a light's transports keep the same fields ({name})"
        values.index_fill_(dim, where, 0.0)
        values.index_copy_(dim, where[found], take_rows(new, dim, source[found]))
