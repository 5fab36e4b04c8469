"""Relighting a multiview cache from any camera: correspondence map, cached lighting, the direct Relighter.

For each new view (`set_view`), the caller's visible points (`ViewPoints`) are matched to caching
camera samples (`correspondence_map`, eq. 5), small holes are filled (`fill_small_holes`), and a
GBuffer is assembled: the new view's own positions, geometric normals and depths with the chosen
samples' material parameters and shading frames, bilinearly resampled (`resample`). Where the
material does not perturb its normal, the view's own smooth normal replaces the cached one (the
frame re-orthonormalised around it): a cached normal is the one at the caching pixel's centre,
which on a curved surface seen by a coarser caching camera is off by up to a caching pixel and
shifts highlights.

Lighting: a camera move changes no light, so nothing about lights is traced again. Per light, the
viewer-independent part of its transport (light samples, radiance, shaping, shadow rays; see
`incident`) is kept for the caching cameras' samples; a view takes its points' entries from the
nearest caching pixel (or, `blend_lighting`, blends the four with their materials' bilinear
weights) and evaluates only the BRDF at its own view direction (`incident.group_images`). The
resulting unit images go to a direct `Relighter` over the view (`Relighter.set_unit_images`),
which applies colour, exposure, light links and light groups as for a single-view cache: there is
no second shading path. Entries are traced lazily, for the caching
samples a view uses and not yet lit (`prepare_lighting` traces them all); an edit of a light's
transform or shaping drops its entries, a colour or link edit keeps them. Three kinds of view
points are traced at the view instead: those on a light's edges in the caching images
(`edge_contrast`: where the caching pixels are coarser than the view's, hard shadow edges would
otherwise come out as their staircase), those in a light's near field (`near_field`: where the
nearest caching sample lies far from the point relative to the light's distance, as on a window
frame next to a rect light, its lighting is not the point's) and the samples baked on demand for
large holes (not in the pool).
"""

from __future__ import annotations

import collections
import dataclasses
import os
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple, cast

import numpy as np
import torch

from relight_torch.cache.layer import CacheDescription, read_cache_layer
from relight_torch.cache.load import check_inputs, load_npy
from relight_torch.direct.loading import embree_visibility, shot_lights
from relight_torch.direct.relighter import Relighter
from relight_torch.direct.rig import replace_rig
from relight_torch.direct.settings import RelightSettings
from relight_torch.errors import RelightError
from relight_torch.gbuffer import GBuffer
from relight_torch.light_samples import bounding_radius, fixed_light_samples
from relight_torch.lights.emission import validate_light
from relight_torch.lights.light import Light, LightKind
from relight_torch.lights.linking import decode_paths
from relight_torch.math.extremes import extremes_of_four
from relight_torch.math.frame import orthonormal_basis
from relight_torch.multiview.correspondence import ViewPoints, correspondence_map
from relight_torch.multiview.holes import HoleReport, fill_small_holes
from relight_torch.multiview.incident import (
    CHANNELS,
    group_images,
    incident_table,
    pool_light_samples,
    sample_groups,
    view_colours,
    view_directions,
)
from relight_torch.multiview.load import load_camera_table, load_view_gbuffers
from relight_torch.multiview.resample import bilinear_samples
from relight_torch.multiview.views import CachingViews, concat_gbuffers, gather_gbuffer, take_rows
from relight_torch.parallel import parallel_map, tile_threads
from relight_torch.protocol import Refinement, refuse_material_edit, refuse_progressive
from relight_torch.visibility.embree import EmbreeCaster


class ViewSamples(NamedTuple):
    """A new view's samples: its GBuffer, hole report, and how its first M rows blend pool rows.

    Attributes:
        gbuffer: the view's covered sub-samples: M rows from the pool, then any baked on demand.
        report: the hole report.
        rows: (M,) int64 the pool row nearest to each of the first M rows (its correspondence).
        taps: (M, 4) int64 pool rows blended into each of the first M rows; weights: (M, 4) float32.
    """

    gbuffer: GBuffer
    report: HoleReport
    rows: torch.Tensor
    taps: torch.Tensor
    weights: torch.Tensor


def view_gbuffer(
    views: CachingViews, view: ViewPoints, patch: GBuffer | None = None, normal_mapped: torch.Tensor | None = None
) -> ViewSamples:
    """The new view's samples from the caching cameras' (see the module docstring).

    Args:
        views: the caching cameras, on the view's device.
        view: the new view's visible points.
        patch: samples baked on demand for (some of) the large holes' pixels, or None: those
            pixels then stay black.
        normal_mapped: (num_materials,) bool, materials whose cached normals are kept; None keeps
            every cached normal (and so does a view without `shading_normal`).

    Returns:
        The GBuffer over the view's (H, W) sub-sample image, the hole report and the blend.
    """
    correspondence = correspondence_map(views, view.position, view.geometric_normal, view.object_id)
    assert correspondence.pixel is not None  # correspondence_map always sets it
    rows, report = fill_small_holes(view, correspondence.pool_row, views.pool)
    keep = torch.nonzero(rows >= 0).squeeze(-1)

    def kept(values: torch.Tensor) -> torch.Tensor:
        return values.index_select(0, keep)

    # Filled holes are resampled at their neighbour's pixel centre: that sample alone.
    matched = kept(correspondence.pool_row) >= 0
    row = kept(rows)
    geometric_normal = kept(view.geometric_normal)
    pixel = torch.where(matched[:, None], kept(correspondence.pixel), views.pool_pixel.index_select(0, row))
    chosen = bilinear_samples(
        views,
        pixel,
        row,
        geometric_normal,
        None if view.shading_normal is None else kept(view.shading_normal),
        normal_mapped,
    )
    gbuffer = GBuffer(
        image_size=view.image_size,
        pixel_index=kept(view.pixel_index),
        position=kept(view.position),
        geometric_normal=geometric_normal,
        depth=kept(view.depth),
        camera_position=view.camera_position,
        **{k: v for k, v in chosen._asdict().items() if k not in ("taps", "weights")},
    )
    taps, weights = chosen.taps, chosen.weights
    if patch is not None:
        if patch.image_size != view.image_size:
            raise ValueError(f"hole patch is for a {patch.image_size} image, the view is {view.image_size}")
        taken = torch.zeros(view.image_size[0] * view.image_size[1], dtype=torch.bool, device=view.position.device)
        taken[gbuffer.pixel_index] = True
        fresh = gather_gbuffer(patch, torch.nonzero(~taken[patch.pixel_index]).squeeze(-1))
        # The frame from the normal alone, as resampling builds it (a baked tangent is zero without UVs).
        tangent, bitangent = orthonormal_basis(torch.nn.functional.normalize(fresh.normal, dim=-1))
        fresh = dataclasses.replace(
            fresh, tangent=tangent.to(fresh.tangent.dtype), bitangent=bitangent.to(fresh.bitangent.dtype)
        )
        gbuffer = concat_gbuffers(
            [gbuffer, fresh], view.image_size, torch.cat([gbuffer.pixel_index, fresh.pixel_index]), view.camera_position
        )
    return ViewSamples(gbuffer, report, row, taps, weights)


class MultiviewRelighter:
    """Direct relighting of a multiview cache from a camera that moves.

    Args:
        views: the caching cameras and their deep framebuffers (device of every computation).
        visibility: shadow queries (traced for the caching samples, once per light edit).
        supersampling: s x s sub-samples per pixel of the new views.
        exposure_scale: the cache's camera exposure scale (`set_view` may change it).
        settings, object_paths: as `Relighter`.
        sample_groups: G, groups of light samples whose BRDF is evaluated together at a view
            (`incident`): the light's sample count (or more) evaluates every sample, fewer trade
            highlight sharpness for speed (1: one BRDF evaluation per light and point).
        blend_lighting: blend the cached lighting of the four caching pixels around a point with
            the materials' bilinear weights; False takes the nearest one's (4x fewer gathers;
            shadow edges then follow the caching camera's pixels).
        edge_contrast: points whose four caching pixels disagree on a light by more than this
            have that light traced again at their own position, so that hard edges come out at
            the view's resolution rather than the caching camera's: the fractions of the light
            reaching them past occluders differ by more (shadow edges), or the unshadowed light
            by more than this fraction of the largest (the edges of a light's pool).
        near_field: points farther from their nearest caching sample than this fraction of their
            distance to a light's bounding sphere have that light traced again at their own
            position (sphere, disk, rect and cylinder lights). With both None a camera move traces
            nothing.

    Attributes:
        caster: Embree over the cache's occluders, for the new views' primary rays.
        occluder_objects: (T,) object id of each occluder triangle (the object of a primary hit).
        corner_normals: (T, 3, 3) smooth normals of the occluders' corners, or None.
        normal_mapped: (num_materials,) bool tensor, materials whose cached normals are kept, or None.
        description: the cache layer's description when opened with `open_multiview_relighter`.
        report: the last view's `HoleReport`.
        counters: 'lit_samples' pool samples whose lighting was traced (per light), 'edge_samples'
            and 'patch_samples' likewise for view points on edges and samples baked on demand,
            'view_shading' (light, view) BRDF passes.
    """

    material_edits = False  # the caching views' materials are shaded as baked (`CacheRelighter`)
    progressive = False  # no coarse frames (`CacheRelighter.refine`)

    def __init__(
        self,
        views: CachingViews,
        visibility,
        supersampling: int = 1,
        exposure_scale: float = 1.0,
        settings: RelightSettings = RelightSettings(),
        object_paths: list[str] | None = None,
        caster: EmbreeCaster | None = None,
        occluder_objects: np.ndarray | None = None,
        corner_normals: np.ndarray | None = None,
        normal_mapped: torch.Tensor | None = None,
        sample_groups: int = 1,
        blend_lighting: bool = False,
        edge_contrast: float | None = 0.8,
        near_field: float | None = 0.1,
    ):
        self.views = views
        self.visibility = visibility
        self.supersampling = supersampling
        self.exposure_scale = exposure_scale
        self.settings = settings
        self.object_paths = object_paths
        self.caster = caster
        self.occluder_objects = occluder_objects
        self.corner_normals = corner_normals
        self.normal_mapped = normal_mapped
        self.sample_groups = sample_groups
        self.blend_lighting = blend_lighting
        self.edge_contrast = edge_contrast
        self.near_field = near_field
        self.description: CacheDescription | None = None
        self.report: HoleReport | None = None
        self.counters: collections.Counter[str] = collections.Counter()
        self._counters_lock = threading.Lock()  # lights are shaded on worker threads (`_shaded`)
        self._lights: dict[str, Light] = {}
        self._edits = 0  # `edits`
        self._relighter: Relighter | None = None
        self._view: ViewSamples | None = None
        self._directions: torch.Tensor | None = None  # (9, N) `incident.view_directions` of the view
        self._colours: torch.Tensor | None = None
        self._edge_taps: torch.Tensor | None = None  # (4, M) the view's taps for `_refined_points`
        # The view's (3, M) positions and (M,) distances to their nearest samples (near field).
        self._offsets: tuple[torch.Tensor, torch.Tensor] | None = None
        # Per light: the pool's (7 G, R) incident table, channels first, which rows are traced, and
        # (2, R) the fraction of the light reaching each row and its summed unshadowed W (what
        # `_refined_points` compares); per sample count, the pool's fixed light samples; (light, taps)
        # whose table holds every row the current view uses (its nearest rows, or with taps its four
        # taps' rows).
        self._tables: dict[str, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}
        self._ready: set[tuple[str, bool]] = set()
        self._u: dict[int, torch.Tensor] = {}
        self._traced_u: dict[int, torch.Tensor] = {}  # per sample count, `_point_samples`' draw
        self._num_samples: dict[str, int] = {}
        # A Relighter over the pool, for the lights' sample counts only (as over a view).
        self._pool_relighter = Relighter(views.pool, visibility, 1, 1.0, settings, object_paths)

    @property
    def relighter(self) -> Relighter:
        """The direct Relighter of the current view."""
        if self._relighter is None:
            raise RelightError("multiview relighter: no view set (call set_view with the new camera's points)")
        return self._relighter

    @property
    def lights(self) -> list[Light]:
        return list(self._lights.values())

    material_paths = None  # no material edits (`CacheRelighter`)

    @property
    def edits(self) -> int:
        """`CacheRelighter.edits`: light additions, edits and removals so far."""
        return self._edits

    def pending(self, stride: int | None) -> int:
        refuse_progressive(self)

    def refine(self, stride: int | None) -> Refinement:
        refuse_progressive(self)

    def set_lights(self, lights: list[Light]) -> None:
        """Replace the whole rig; unchanged lights keep their cached lighting."""
        replace_rig(self, lights)

    def set_light(self, light: Light) -> None:
        """Add or edit a light: an edit of its transform or shaping drops its cached lighting.

        Raises:
            ValueError: the light is one the kernels cannot honour (`emission.validate_light`).
        """
        validate_light(light)
        relighter = self._relighter
        had = relighter is not None and light.path in self._lights and relighter.unit_images(light.path) is not None
        self._lights[light.path] = light
        self._edits += 1
        if relighter is not None:
            relighter.set_light(light)
        if not (had and relighter is not None and relighter.unit_images(light.path) is not None):
            self._tables.pop(light.path, None)
            self._num_samples.pop(light.path, None)
            self._ready -= {(light.path, False), (light.path, True)}

    def remove_light(self, path: str) -> None:
        self._edits += 1
        self._lights.pop(path, None)
        self._tables.pop(path, None)
        self._num_samples.pop(path, None)
        self._ready -= {(path, False), (path, True)}
        if self._relighter is not None and path in {light.path for light in self._relighter.lights}:
            self._relighter.remove_light(path)

    def set_view(
        self, view: ViewPoints, patch: GBuffer | None = None, exposure_scale: float | None = None
    ) -> HoleReport:
        """Move to a new view: correspondence map, hole filling, and a Relighter over it (no tracing)."""
        if exposure_scale is not None:
            self.exposure_scale = exposure_scale
        self._view = view_gbuffer(self.views, view.to(self.views.device), patch, self.normal_mapped)
        gbuffer = self._view.gbuffer
        self._directions = view_directions(gbuffer.wo_world(), gbuffer.normal, gbuffer.geometric_normal)
        self._colours = view_colours(gbuffer.params)
        self._edge_taps = self._offsets = None
        self._ready.clear()
        self.report = self._view.report
        self._relighter = Relighter(
            gbuffer, self.visibility, self.supersampling, self.exposure_scale, self.settings, self.object_paths
        )
        self._relighter.set_lights(self.lights)
        return self.report

    def prepare_lighting(self) -> None:
        """Trace every light's lighting at every caching sample now (later views then trace nothing)."""
        every = torch.arange(self.views.pool.num_samples, device=self.views.device)
        for light in self._lights.values():
            self._pool_table(light, every)

    def lighting_bytes(self) -> int:
        """Bytes of the cached per-light lighting of the caching samples."""
        return sum(
            table.numel() * table.element_size() + done.numel() + total.numel() * total.element_size()
            for table, done, total in self._tables.values()
        )

    def held_bytes(self) -> int:
        """`CacheRelighter.held_bytes`: the caching samples' lighting and the current view's relighter."""
        return self.lighting_bytes() + (0 if self._relighter is None else self._relighter.held_bytes())

    def set_material_edits(self, edits: Mapping[int | str, Mapping[str, object]]) -> None:
        refuse_material_edit(self)

    def edit_material(self, material: int | str, **values: object) -> None:
        refuse_material_edit(self)

    def render(self) -> torch.Tensor:
        """(H, W, 3) linear image of the current view."""
        return self._shaded().render()

    def light_image(self, path: str) -> torch.Tensor:
        return self._shaded().light_image(path)

    def light_group_images(self) -> dict[str, torch.Tensor]:
        return self._shaded().light_group_images()

    def emission_image(self) -> torch.Tensor:
        return self._shaded().emission_image()

    def _shaded(self) -> Relighter:
        """The view's Relighter with every light's unit images given (from the cached lighting).

        The lights' images are made on the kept worker threads (`relight_torch.parallel`), a light
        each: most of a light's work at a view is short passes over its edge points, which one
        torch thread per light runs better than two threads per pass."""
        relighter = self.relighter
        missing = [light for light in self._lights.values() if relighter.unit_images(light.path) is None]
        threads = tile_threads(self.views.device, self.visibility.thread_safe)
        for light, images in zip(missing, parallel_map(self._view_images, missing, threads), strict=True):
            relighter.set_unit_images(light.path, images)
        return relighter

    def _count(self, name: str, value: int) -> None:
        """Add `value` to counter `name` (from any thread)."""
        with self._counters_lock:
            self.counters[name] += value

    def _light_samples(self, light: Light) -> torch.Tensor:
        """(R, S, 2) the pool's fixed light samples for the light's sample count (found once per
        light: it depends on the light's shape and position, whose edits drop it with the table)."""
        if light.path not in self._num_samples:
            self._num_samples[light.path] = self._pool_relighter.num_light_samples(light)
        num_samples = self._num_samples[light.path]
        if num_samples not in self._u:
            views, counts = self.views, torch.bincount(self.views.pool_view, minlength=self.views.num_views)
            self._u[num_samples] = pool_light_samples(
                counts.tolist(), num_samples, self.settings.seed, views.device, views.pool.position.dtype
            )
        return self._u[num_samples]

    def _point_samples(self, num_points: int, num_samples: int) -> torch.Tensor:
        """(num_points, S, 2) fixed light samples for view points traced at their own position: the
        first rows of one draw kept for the relighter's life (`fixed_light_samples` draws row by row
        from one seeded generator, so these equal a draw of num_points; kept, each render skips it)."""
        drawn = self._traced_u.get(num_samples)
        if drawn is None or drawn.shape[0] < num_points:
            size = max(num_points, 0 if drawn is None else 2 * drawn.shape[0])
            drawn = fixed_light_samples(
                size, num_samples, self.settings.seed, self.views.device, self.views.pool.position.dtype
            )
            self._traced_u[num_samples] = drawn
        return drawn[:num_points]

    def _pool_table(self, light: Light, rows: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """The light's (7 G, R) incident table (channels first, `incident.CHANNELS`) and (2, R) each row's
        fraction of the light reaching it past occluders (summed W over summed unshadowed W, 0 where
        that is 0) and its summed unshadowed W, with at least `rows` traced (None: the current view's,
        checked once per view and light)."""
        pool = self.views.pool
        u = self._light_samples(light)
        if light.path not in self._tables:
            groups = int(sample_groups(u.shape[1], self.sample_groups).max()) + 1
            self._tables[light.path] = (
                pool.position.new_zeros(CHANNELS * groups, pool.num_samples),
                torch.zeros(pool.num_samples, dtype=torch.bool, device=pool.device),
                pool.position.new_zeros(2, pool.num_samples),
            )
        table, done, total = self._tables[light.path]
        taps = self.blend_lighting or self.edge_contrast is not None
        ready = (light.path, taps) if rows is None else None
        if ready is not None:
            if ready in self._ready:
                return table, total
            assert self._view is not None  # set_view comes before any image
            rows = self._view.taps.reshape(-1) if taps else self._view.rows
        assert rows is not None  # given, or the view's
        missing = rows.new_zeros(0) if bool(done.all()) else torch.unique(rows[~done.index_select(0, rows)])
        if missing.numel():

            def pick(values: torch.Tensor) -> torch.Tensor:
                return values.index_select(0, missing)

            traced, unshadowed = incident_table(
                light,
                pick(pool.position),
                pick(pool.geometric_normal),
                pick(pool.normal),
                pick(u),
                self.visibility,
                self.sample_groups,
                self.settings.chunk_samples,
            )
            table.index_copy_(1, missing, traced.permute(2, 1, 0).reshape(table.shape[0], -1))
            reaching = traced[..., :3].sum((1, 2)).div_(torch.where(unshadowed > 0, unshadowed, 1.0))
            total.index_copy_(1, missing, torch.stack([reaching, unshadowed]))
            done[missing] = True
            self._count("lit_samples", int(missing.numel()))
        if ready is not None:
            self._ready.add(ready)
        return table, total

    def _view_images(self, light: Light) -> torch.Tensor:
        """(2, N, 3) the light's unit images at the view: cached lighting, the view's BRDF."""
        view, directions = self._view, self._directions
        assert view is not None and directions is not None  # set_view comes before any image
        gbuffer = view.gbuffer
        refine = self.edge_contrast is not None or self.near_field is not None
        table, totals = self._pool_table(light, None)
        if self.blend_lighting:
            # Four taps: never the empty sum's 0.
            columns = cast(
                torch.Tensor,
                sum(take_rows(table, view.taps[:, t]) * view.weights[:, t] for t in range(view.taps.shape[1])),
            )
        else:
            columns = take_rows(table, view.rows)
        cached = view.rows.shape[0]
        # Traced at the view: the points on the light's edges in the caching images or in its near field,
        # and the samples baked on demand (not in the pool).
        traced = [self._refined_points(light, totals)] if refine else []
        self._count("edge_samples", int(traced[0].numel()) if refine else 0)
        if gbuffer.num_samples > cached:
            columns = torch.cat([columns, columns.new_zeros(columns.shape[0], gbuffer.num_samples - cached)], 1)
            traced.append(torch.arange(cached, gbuffer.num_samples, device=gbuffer.device))
            self._count("patch_samples", gbuffer.num_samples - cached)
        points = torch.cat(traced) if traced else None
        if points is not None and points.numel():

            def pick(values: torch.Tensor) -> torch.Tensor:
                return values.index_select(0, points)

            u = self._point_samples(points.numel(), self._light_samples(light).shape[1])
            fresh, _ = incident_table(
                light,
                pick(gbuffer.position),
                pick(gbuffer.geometric_normal),
                pick(gbuffer.normal),
                u,
                self.visibility,
                self.sample_groups,
                self.settings.chunk_samples,
            )
            columns.index_copy_(1, points, fresh.permute(2, 1, 0).reshape(columns.shape[0], -1))
        self._count("view_shading", 1)
        # The group count spelt out: with no covered sample (only sky) -1 would be ambiguous.
        groups = columns.shape[0] // CHANNELS
        return group_images(
            gbuffer.params, directions, columns.reshape(CHANNELS, groups, gbuffer.num_samples), self._colours
        )

    def _refined_points(self, light: Light, totals: torch.Tensor) -> torch.Tensor:
        """(E,) int64 rows of the view traced at their own position for `light`: with `edge_contrast` c,
        those whose four caching taps (those of its surface) disagree on the light (`totals`, (2, R),
        `_pool_table`'s): the fractions of the light reaching them past occluders differ by more
        than c (shadow edges sharper than a caching pixel), or the unshadowed W differs by more
        than c of the largest (the edges of a light's pool: cone, shaping, the horizon); with
        `near_field`, those whose nearest caching sample is farther from them than that fraction
        of their distance to the light's bounding sphere."""
        view = self._view
        assert view is not None  # set_view comes before any image
        count = view.rows.shape[0]
        refined = torch.zeros(count, dtype=torch.bool, device=totals.device)
        if self.edge_contrast is not None:
            if self._edge_taps is None:
                # (4, M): taps of another surface (weight 0) stand in for the nearest one, which always
                # counts; rows of taps, so that the extremes are three element-wise maxima and minima.
                self._edge_taps = torch.where(view.weights > 0, view.taps, view.rows[:, None]).T.contiguous()
            reaching, unshadowed = take_rows(totals, self._edge_taps).unbind(0)  # (4, M) each
            high, low = extremes_of_four(reaching)
            refined |= high - low > self.edge_contrast
            high, low = extremes_of_four(unshadowed)
            refined |= high - low > self.edge_contrast * high
        if self.near_field is not None and light.kind not in (LightKind.DISTANT, LightKind.DOME):
            if self._offsets is None:
                position = view.gbuffer.position[:count].T.contiguous()  # (3, M)
                offset = position - self.views.pool.position.index_select(0, view.rows).T
                self._offsets = position, (offset * offset).sum(0).sqrt_()
            position, offsets = self._offsets
            centre = light.world_from_light[:3, 3]
            squared = (position[0] - float(centre[0])).square_()
            for axis in (1, 2):
                squared.add_((position[axis] - float(centre[axis])).square_())
            refined |= offsets > self.near_field * (squared.sqrt_() - bounding_radius(light))
        return torch.nonzero(refined).squeeze(-1)


def open_multiview_relighter(
    path: str | os.PathLike[str],
    device: str | torch.device = "cpu",
    shadows: str = "embree",
    lights_layer: str | os.PathLike[str] | None = None,
    settings: RelightSettings = RelightSettings(),
    sample_groups: int = 1,
    blend_lighting: bool = False,
    edge_contrast: float | None = 0.8,
    near_field: float | None = 0.1,
) -> MultiviewRelighter:
    """A MultiviewRelighter for a 'multiview' cache layer, with the shot's lights (and `lights_layer`'s).

    No view is set: give it one with `set_view` (`pipeline.bake.multiview.view.view_points` traces
    a camera's primary rays against `relighter.caster`).

    Raises:
        RelightError: the layer is unreadable, not multiview, stale or corrupt, or `shadows` is not
            'embree' (shadow maps are fitted to one view's receivers).
    """
    layer_path = Path(path)
    description = read_cache_layer(layer_path)
    if description.method != "multiview":
        raise RelightError(f"{layer_path}: a {description.method!r} cache, not 'multiview'")
    if shadows != "embree":
        raise RelightError(f"{layer_path}: multiview caches relight with shadows='embree' only, got {shadows!r}")
    check_inputs(layer_path, description)
    table = load_camera_table(layer_path, description)
    views = CachingViews.build(table, [g.to(device) for g in load_view_gbuffers(layer_path, description, table)])
    occluders = load_npy(layer_path, description, "occluders")  # mapped: Embree copies it in blocks
    occluder_objects = np.asarray(load_npy(layer_path, description, "occluderObjects"))
    object_paths = decode_paths(load_npy(layer_path, description, "objectPaths"))
    corner_normals = np.asarray(load_npy(layer_path, description, "cornerNormals"))
    normal_mapped = torch.from_numpy(np.array(load_npy(layer_path, description, "normalMapped"), bool)).to(device)
    caster, visibility = embree_visibility(occluders, occluder_objects, object_paths)
    relighter = MultiviewRelighter(
        views,
        visibility,
        description.supersampling,
        description.exposure_scale,
        settings,
        object_paths,
        caster,
        occluder_objects,
        corner_normals,
        normal_mapped,
        sample_groups,
        blend_lighting,
        edge_contrast,
        near_field,
    )
    relighter.description = description
    relighter.set_lights(shot_lights(description, lights_layer))
    return relighter
