"""The relighter: direct light on a deep framebuffer, re-rendering only what an edit touches.

Light is linear, so the image is a sum over lights of

    colour_scale(light) x (diffuse x diffuse_image(light) + specular x specular_image(light))

where colour_scale = intensity 2^exposure color [blackbody], `diffuse` / `specular` are the
light's per-lobe multipliers, and the two images are the light's diffuse and specular reflection
with those set to 1. Per light the relighter keeps three stages, each recomputed only when its
inputs change:

    transport   <- transform, size, kind, texture, shadow settings     ('visibility' counter)
        light samples of the unshaped unit light, their shadow rays, and per live sample the
        diffuse and specular f cos(theta_i) L_i V / (pdf S), kept only at the shading points
        the light reaches (facing it, not fully shadowed)
    images      <- the above + ShapingAPI and Barzel controls            ('shading' counter)
        the shaping factor of each live sample times its transport, summed per point
    scale       <- intensity, exposure, color, colour temperature, diffuse, specular (a multiply)
    mask        <- light link                                         ('masks' counter)
        which shading points' objects the light illuminates (UsdLux `collection:lightLink`,
        resolved against the cache's object paths): the images stay unmasked, so a light-link
        edit recomputes only this (N,) mask. A shadow-link edit changes which occluders cast
        the light's shadows: its transport is traced again.

Shaping multiplies the radiance a light emits towards a receiver, and nothing else depends on it,
so a shaping edit re-weights the cached transport without tracing or shading again (the
deep-framebuffer split of Gershbein & Hanrahan 2000: surface terms cached, light shaders re-run).
The sum of all lights but the last one edited is cached, so editing one light's colour costs two
multiply-adds over the image.

Area lights and domes use fixed stratified samples per shading point (`light_samples`), so the
image does not flicker while a light is edited; `RelightSettings.full_sampling_angle` gives small
lights fewer samples (their count then changes in steps as a light moves). `counters` counts
visibility and shading passes (tests use it to check that a colour edit shades nothing).
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from relight_torch.brdf import preview_surface
from relight_torch.cache.layer import CacheDescription, read_cache_layer
from relight_torch.cache.load import check_inputs, load_gbuffer, load_npy
from relight_torch.direct import gradients
from relight_torch.direct.gradients import GEOMETRY_KINDS
from relight_torch.direct.settings import RelightSettings, auto_filter_radius, default_memory_budget
from relight_torch.direct.sharing import PixelGroups
from relight_torch.direct.transport import Transport
from relight_torch.errors import RelightError
from relight_torch.gbuffer import GBuffer
from relight_torch.levels import Level, build_level
from relight_torch.light_samples import adaptive_sample_count, angular_radius, fixed_light_samples
from relight_torch.lights.emission import is_delta_light, light_radiance_scale, sample_light, validate_light
from relight_torch.lights.light import Light, LightKind, light_snapshot, lights_equal
from relight_torch.lights.linking import decode_paths, linked_points
from relight_torch.lights.ratio import closed_form, has_closed_form, ratio_of
from relight_torch.lights.shadow import shadow_factor, shadow_strength
from relight_torch.lights.shaping import emission_factor
from relight_torch.lights.usd import read_stage_lights
from relight_torch.math.frame import dot, to_local
from relight_torch.parallel import parallel_map, tile_threads
from relight_torch.protocol import CacheRelighter, Refinement, refuse_material_edit
from relight_torch.stage import check_composition, defining_layer, open_stage, outside_reads, time_code
from relight_torch.visibility import Visibility
from relight_torch.visibility.embree import EmbreeCaster, ShadowLinkCasters
from relight_torch.visibility.opacity import OPACITY_PAYLOADS, OpacityTable
from relight_torch.visibility.rays import RayVisibility
from relight_torch.visibility.shadow_maps import ShadowMapVisibility
from relight_torch.visibility.surface_filter import SurfaceFilter

_COLOUR_FIELDS = (
    "intensity",
    "exposure",
    "color",
    "enable_color_temperature",
    "color_temperature",
    "diffuse",
    "specular",
)
_SHADING_FIELDS = ("shaping", "barzel")
# Pixels per row when a colour scale is applied (see Relighter._add_light).
_TILE_PIXELS = 1024
# The kinds whose emission ShapingAPI and Barzel controls shape (see lights/emission.py).
_SHAPED_KINDS = (LightKind.SPHERE, LightKind.RECT, LightKind.DISK, LightKind.CYLINDER)


def box_filter(image: torch.Tensor, s: int) -> torch.Tensor:
    """The mean of each s x s block of an (H, W, C) image: (H / s, W / s, C).

    Summed as slabs (s rows of W C values, then s runs of C values), which torch's CPU kernels
    stream; `reshape(H / s, s, W / s, s, C).mean((1, 3))`, the same numbers, runs ~10x slower.
    """
    height, width, channels = image.shape
    rows = image.reshape(height // s, s, width * channels)
    total = sum((rows[:, k] for k in range(1, s)), rows[:, 0])
    runs = total.reshape(height // s, width // s, s * channels)
    total = sum((runs[..., k * channels : (k + 1) * channels] for k in range(1, s)), runs[..., :channels])
    return total / (s * s)


def _take(values: torch.Tensor, rows: slice | torch.Tensor) -> torch.Tensor:
    """values[rows] along the first axis: a slice as a view, indices through `index_select` (the
    advanced index `values[rows]` of a few thousand rows of a million-row tensor ran ~100x slower
    on the CPU: ~7 ms against 0.03 ms, torch 2.13)."""
    return values[rows] if isinstance(rows, slice) else values.index_select(0, rows)


def _reorder(values: torch.Tensor | None, order: torch.Tensor) -> torch.Tensor | None:
    return None if values is None else values.index_select(0, order)


def _key(light: Light, names: tuple[str, ...]) -> tuple[object, ...]:
    """A hashable snapshot of some fields of a light (arrays by content, `light_snapshot`)."""
    return tuple(light_snapshot(getattr(light, name)) for name in names)


def _geometry_fields() -> tuple[str, ...]:
    skip = set(_COLOUR_FIELDS) | set(_SHADING_FIELDS) | {"path", "light_group", "light_link"}
    return tuple(f.name for f in dataclasses.fields(Light) if f.name not in skip)


_GEOMETRY_FIELDS = _geometry_fields()


def geometry_key(light: Light) -> tuple[object, ...]:
    """A hashable snapshot of what a light's shadow rays and light samples depend on (not its
    colour, shaping, path, group or link)."""
    return _key(light, _GEOMETRY_FIELDS)


def replace_rig(relighter: CacheRelighter, lights: list[Light]) -> None:
    """Make `lights` a relighter's whole rig through its `remove_light` and `set_light` (lights
    matched by path), so that unchanged lights keep their cached work."""
    for path in {light.path for light in relighter.lights} - {light.path for light in lights}:
        relighter.remove_light(path)
    for light in lights:
        relighter.set_light(light)


def light_group(light: Light) -> str:
    """The light-group AOV a light writes to: its `light_group`, else its prim's name."""
    return light.light_group or light.path.rsplit("/", 1)[-1]


def unit_light(light: Light) -> Light:
    """The light with intensity 1, exposure 0, white colour and no colour temperature."""
    return dataclasses.replace(
        light, intensity=1.0, exposure=0.0, color=(1.0, 1.0, 1.0), enable_color_temperature=False
    )


def colour_scale(light: Light) -> np.ndarray:
    """(3,) factor turning the light's unit image into its image (see the module doc)."""
    unit = light_radiance_scale(unit_light(light))
    full = light_radiance_scale(light)
    scale: np.ndarray = np.divide(full, unit, out=np.zeros(3), where=unit != 0)
    return scale


@dataclass
class _Progress:
    """A light's unit images made point by point (progressive refinement, `Relighter.refine`).

    Attributes:
        images: (2, N, 3) diffuse and specular unit images at the points done, undefined elsewhere
            (allocated, not zeroed: a coarse frame's first work should not be a pass over N).
        done: (N,) bool, the points done.
        num_done: their count.
        samples_per_point: the light's samples per point, averaged over the points (its sample
            groups, `Relighter._sample_groups`): the work a point costs, for `pending`.
        parts: per sample group, the transports traced so far and the points they were traced
            for, kept (where the memory budget allows it) to become the light's transport once
            every point is done, so that a later shaping edit traces nothing; None: not kept.
        traced: whether they come from shadow rays traced for them (the light kept no transport)
            or from its kept transport.
        shadow_sums: (N, 2) sum_s w V and sum_s w at the points done, for a traced light whose
            visibility is filtered (`Transport.shadow_sums`): its filtered visibility needs every
            point's sums and multiplies `images[0]` once the last point is done. None otherwise.
    """

    images: torch.Tensor
    done: torch.Tensor
    traced: bool
    samples_per_point: float
    num_done: int = 0
    shadow_sums: torch.Tensor | None = None
    parts: list[list[tuple[torch.Tensor, Transport]]] | None = None

    @property
    def num_bytes(self) -> int:
        tensors = (self.images, self.done, self.shadow_sums)
        kept = sum(part.num_bytes for group in self.parts or () for _, part in group)
        return kept + sum(t.numel() * t.element_size() for t in tensors if t is not None)


@dataclass
class _LightState:
    light: Light
    geometry_key: tuple[object, ...]
    shading_key: tuple[object, ...]
    transports: list[Transport] | None = None  # one per sample group (`Relighter._sample_groups`)
    images: torch.Tensor | None = None  # (2, N, 3) diffuse and specular unit images
    edited: int = 0  # when it was last set (`Relighter._edits`): the budget drops the oldest first
    progress: _Progress | None = None  # `images` made so far, point by point, while they are None
    # Folded: its image is part of `Relighter._folded` and its own images were dropped (the budget).
    folded: bool = False
    external: bool = False  # its images came from `set_unit_images`: they cannot be made again here


class Relighter:
    """Direct relighting of one deep framebuffer.

    Args:
        gbuffer: the covered sub-samples (device and dtype of every computation).
        visibility: shadow queries (Embree rays or torch shadow maps).
        supersampling: s; the sub-sample image is box-filtered by s x s after shading.
        exposure_scale: the camera's linear exposure scale.
        settings: sampling settings.
        object_paths: the prim path of each object id of the G-buffer, to resolve light links
            against; None when unknown (lights with a light link are then refused).

    Attributes:
        description: the cache layer's description when opened with `open_relighter`.
        counters: 'visibility', 'shading' and 'masks' passes run so far (one per light and stage).
    """

    material_edits = False  # the baked materials are shaded as they are (`CacheRelighter`)
    # The `--free` kinds `relight solve` may differentiate through this relighter
    # (`protocol.GradientRelighter`, `relight_torch.direct.gradients`).
    gradient_kinds = frozenset(GEOMETRY_KINDS)
    progressive = True  # `pending` and `refine` (`CacheRelighter`)

    def __init__(
        self,
        gbuffer: GBuffer,
        visibility: Visibility,
        supersampling: int = 1,
        exposure_scale: float = 1.0,
        settings: RelightSettings = RelightSettings(),
        object_paths: list[str] | None = None,
    ):
        height, width = gbuffer.image_size
        if height % supersampling or width % supersampling:
            raise ValueError(f"image {width}x{height} is not a multiple of supersampling {supersampling}")
        self.gbuffer = gbuffer
        self.visibility = visibility
        self.supersampling = supersampling
        self.exposure_scale = exposure_scale
        self.settings = settings
        self.filter_radius = (
            auto_filter_radius(gbuffer.image_size, supersampling)
            if settings.shadow_filter_radius is None
            else settings.shadow_filter_radius
        )
        self.counters: collections.Counter[str] = collections.Counter()
        self.description: CacheDescription | None = None
        self.object_paths = object_paths
        self._lights: dict[str, _LightState] = {}
        self._masks: dict[tuple[str, ...], torch.Tensor] = {}
        # (wo, N.E / |N|, 1 / |N|) of every point, made on first use (`_view_directions`).
        self._viewer: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
        # Whether the transport factors carry the clearcoat lobe: one answer for every chunk.
        self._coat = bool(gbuffer.params.clearcoat.any())
        # The glossy and the matte points, or None for both when the image is all one kind.
        glossy = preview_surface.glossy(gbuffer.params)
        self._all_glossy = bool(glossy.all())
        self._glossy_split = None
        if glossy.any() and not self._all_glossy:
            self._glossy_split = (torch.nonzero(~glossy).squeeze(-1), torch.nonzero(glossy).squeeze(-1))
        self._factor_colours: torch.Tensor | None = None  # (F, N, 3), made on first use
        # The sub-samples that share their light (`direct.sharing`), or None.
        sharing = settings.shared_lighting and supersampling > 1 and self.filter_radius > 0
        self._groups = PixelGroups(gbuffer, supersampling) if sharing else None
        self._group_points: dict[int, _Points] = {}  # the groups as shading points, by samples per point
        self._u: dict[int, torch.Tensor] = {}
        # Every pixel covered in order: scattering into the image is a reshape.
        self._dense = gbuffer.num_samples == height * width and bool(
            (gbuffer.pixel_index == torch.arange(height * width, device=gbuffer.device)).all()
        )
        # Emission plus every light but `_active` (the last one edited), or None when stale.
        self._active: str | None = None
        self._others: torch.Tensor | None = None
        self._surface_filter: SurfaceFilter | None = None
        self.memory_budget = default_memory_budget() if settings.memory_budget is None else settings.memory_budget
        if self.memory_budget < 0:
            raise ValueError(f"memory_budget must be >= 0 bytes, got {self.memory_budget}")
        self._half_images = False  # set once the budget asks for half-precision unit images
        # (N, 3) the summed light of the folded lights (`_fold`), or None while none is.
        self._folded: torch.Tensor | None = None
        # Counts changes of the rig: each light's last one orders what the budget drops, and the
        # lights changed after the last exact frame (`_exact_edits`) are those a coarse frame refines.
        self._edits = 0
        self._exact_edits = 0
        self._levels: dict[int, Level] = {}  # progressive refinement's coarse levels, by stride
        # (key, (H, W, 3) image) of the lights a coarse frame shows exactly (`_static_image`).
        self._static: tuple[object, torch.Tensor] | None = None

    # -- lights ---------------------------------------------------------------------------------

    @property
    def lights(self) -> list[Light]:
        return [state.light for state in self._lights.values()]

    def set_lights(self, lights: list[Light]) -> None:
        """Replace the whole rig; unchanged lights keep their cached work."""
        replace_rig(self, lights)

    def set_light(self, light: Light) -> None:
        """Add a light or edit one (matched by path); invalidates only what the edit touches.

        Raises:
            ValueError: the light is one the kernels cannot honour (`emission.validate_light`).
        """
        validate_light(light)
        transport_key = geometry_key(light)
        shading_key = transport_key + _key(light, _SHADING_FIELDS)
        state = self._lights.get(light.path)
        if state is not None and lights_equal(state.light, light):
            return  # no change: nothing to redo, nothing for progressive refinement to refine
        if state is not None and state.folded:
            self._unfold(state)
        if state is None or state.geometry_key != transport_key:
            state = _LightState(light, transport_key, shading_key)
        elif state.shading_key != shading_key:
            state.images, state.shading_key, state.progress = None, shading_key, None
        state.light = light
        self._edits += 1
        state.edited = self._edits
        self._lights[light.path] = state
        if light.path != self._active:
            self._active, self._others = light.path, None

    @classmethod
    def from_cache(
        cls,
        path: str | os.PathLike[str],
        device: str | torch.device = "cpu",
        shadows: str = "embree",
        lights_layer: str | os.PathLike[str] | None = None,
        settings: RelightSettings = RelightSettings(),
    ) -> Relighter:
        """The direct relighter of a cache layer, checked before loading: see `open_relighter`."""
        return open_relighter(path, device, shadows, lights_layer, settings)

    def remove_light(self, path: str) -> None:
        if path not in self._lights:
            raise KeyError(f"no light {path!r} in the relighter (has {sorted(self._lights)})")
        if self._lights[path].folded:
            self._unfold(self._lights[path])
        del self._lights[path]
        self._others = None
        self._edits += 1

    def invalidate(self, visibility: bool = False) -> None:
        """Drop every light's images (and with `visibility`, its transport): the next render
        shades (and traces) them again. For benchmarks and to free memory."""
        for state in self._lights.values():
            state.images = None
            if visibility:
                state.transports = None
        self._others = None

    def cache_bytes(self) -> int:
        """Bytes held by the per-light caches (transport and images, the folded lights' sum)."""
        total = self._folded.numel() * self._folded.element_size() if self._folded is not None else 0
        for state in self._lights.values():
            total += sum(transport.num_bytes for transport in state.transports or ())
            total += state.images.numel() * state.images.element_size() if state.images is not None else 0
            total += state.progress.num_bytes if state.progress is not None else 0
        return total

    def held_bytes(self) -> int:
        """`CacheRelighter.held_bytes`: the per-light caches (`cache_bytes`)."""
        return self.cache_bytes()

    def edit_material(self, material_id: int, **values: object) -> None:
        refuse_material_edit(self)

    def unit_images(self, path: str) -> torch.Tensor | None:
        """Light `path`'s cached diffuse and specular unit images (2, N, 3); None before it is shaded
        and after an edit of its transform or shaping dropped them (`set_light`)."""
        return self._lights[path].images

    def set_unit_images(self, path: str, images: torch.Tensor) -> None:
        """Give light `path` unit images (2, N, 3) computed elsewhere (the multiview relighter
        gathers them from its caching cameras): `render` then traces and shades nothing for it
        until an edit of its transform or shaping drops them."""
        state = self._lights[path]
        if state.folded:
            self._unfold(state)
        state.images, state.progress, state.external = images, None, True
        self._others = None

    # -- rendering ------------------------------------------------------------------------------

    def render_samples(self) -> torch.Tensor:
        """(N, 3) radiance of every covered sub-sample (camera exposure not applied)."""
        self._exact_edits = self._edits
        if self._others is None:
            self._others = self.gbuffer.params.emissive_color.clone()
            if self._folded is not None:
                self._others += self._folded
            for path, state in self._lights.items():
                if path != self._active and not state.folded:
                    self._add_light(self._others, state)
        if self._active not in self._lights:
            values = self._others.clone()
        else:
            values = self._add_light(self._others, self._lights[self._active], in_place=False)
        self._fold_to_budget()
        return values

    def render(self) -> torch.Tensor:
        """(H, W, 3) linear image: sub-samples shaded, box-filtered, camera exposure applied."""
        return self.to_image(self.render_samples())

    def light_image(self, path: str) -> torch.Tensor:
        """(H, W, 3) image of one light alone (for AOVs and tests)."""
        return self.to_image(self._add_light(torch.zeros_like(self.gbuffer.position), self._lights[path]))

    def light_group_images(self) -> dict[str, torch.Tensor]:
        """Light group (`light_group`) -> (H, W, 3) image of its lights, in the order groups first appear.

        With `emission_image()` the groups' images sum to `render()` (within float rounding).
        """
        totals: dict[str, torch.Tensor] = {}
        for state in self._lights.values():
            group = light_group(state.light)
            if group not in totals:
                totals[group] = torch.zeros_like(self.gbuffer.position)
            self._add_light(totals[group], state)
        return {group: self.to_image(total) for group, total in totals.items()}

    def emission_image(self) -> torch.Tensor:
        """(H, W, 3) the surfaces' own emission (UsdPreviewSurface emissiveColor), no light's."""
        return self.to_image(self.gbuffer.params.emissive_color)

    def scene_diagonal(self) -> float:
        """`protocol.GradientRelighter.scene_diagonal` (1 for an image that covers nothing)."""
        position = self.gbuffer.position
        if position.shape[0] == 0:
            return 1.0
        return float((position.amax(0) - position.amin(0)).norm()) or 1.0

    def freeze_light(self, light: Light, pose: gradients.LightPose, num_samples: int) -> gradients.FrozenVisibility:
        """`protocol.GradientRelighter.freeze_light`: the light's shadow rays at `pose`, traced once."""
        return gradients.freeze_visibility(self, light, pose, num_samples)

    def differentiable_light_image(
        self, light: Light, pose: gradients.LightPose, frozen: gradients.FrozenVisibility
    ) -> torch.Tensor:
        """`protocol.GradientRelighter.differentiable_light_image`: (H, W, 3) unit image at `pose`."""
        return gradients.light_image(self, light, pose, frozen)

    def to_image(self, values: torch.Tensor) -> torch.Tensor:
        """Sub-sample values (N, 3) to the (H, W, 3) image: scattered, box-filtered, exposed."""
        height, width = self.gbuffer.image_size
        image = values.reshape(height, width, 3) if self._dense else self.gbuffer.scatter(values)
        if self.supersampling > 1:
            image = box_filter(image, self.supersampling)
        return image * self.exposure_scale if self.exposure_scale != 1.0 else image

    # -- progressive refinement (`CacheRelighter.refine`, `relight_torch.progressive`) ----------

    @property
    def edits(self) -> int:
        """`CacheRelighter.edits`: light additions, edits and removals so far."""
        return self._edits

    def pending(self, stride: int | None) -> float:
        """`CacheRelighter.pending`: light samples still to evaluate for the changed lights at
        `stride` (points times their samples)."""
        points = None if stride is None else self._level(stride).points
        total = 0.0
        for state in self._changed():
            if state.images is None:
                progress = self._progress(state)
                if points is None:
                    todo = progress.done.shape[0] - progress.num_done
                elif progress.num_done == 0:  # just edited: no pass over the level's points
                    todo = points.shape[0]
                else:
                    todo = int((~_take(progress.done, points)).sum())
                total += todo * progress.samples_per_point
        return total

    def refine(self, stride: int | None) -> Refinement:
        """`CacheRelighter.refine`: the lights changed since the last exact frame (`render()`)
        shaded at one point per `stride` x `stride` pixels (`relight_torch.levels`), the points
        they still lacked traced (or shaded from their kept transport) and kept; their light
        upsampled edge-aware and added to the exact image of the others. `stride` None: every
        point, then `render()`."""
        if stride is None or not self._changed():
            evaluated, work = self.complete()  # before render(), which would shade the rest whole
            return Refinement(self.render(), evaluated, work, True)
        level, values, evaluated, work = self.coarse_values(stride)
        return Refinement(self.coarse_image(level, values), evaluated, work, False)

    def changed_lights(self) -> list[Light]:
        """The lights set since the last exact frame (`render()`), which a coarse frame refines."""
        return [state.light for state in self._changed()]

    def unchanged_key(self) -> tuple[object, ...]:
        """A key of the lights not set since the last exact frame: equal keys, equal lights."""
        return tuple((path, state.edited) for path, state in self._lights.items() if state.edited <= self._exact_edits)

    def complete(self) -> tuple[int, float]:
        """Shade every point the changed lights still lack (their unit images complete); returns
        the light evaluations and the light samples made (`Refinement`)."""
        evaluated, work = 0, 0.0
        for state in self._changed():
            if state.images is None:
                points, samples = self._refine_points(state, None)
                evaluated, work = evaluated + points, work + samples
        return evaluated, work

    def coarse_values(self, stride: int) -> tuple[Level, torch.Tensor, int, float]:
        """(level, values (M, C), light evaluations, light samples made): the changed lights'
        light at the points of the level of `stride` pixels (camera exposure not applied), the
        points they lacked shaded and kept. values[:, :3] is light; each light whose visibility
        will be filtered, while it is made, adds five columns for `coarse_image`: its unshadowed
        diffuse light (3) and its per-point sums of w V and w (2)."""
        level = self._level(stride)
        values = self.gbuffer.position.new_zeros(level.points.shape[0], 3)
        columns = [values]
        evaluated, work = 0, 0.0
        for state in self._changed():
            if state.images is None:
                points, samples = self._refine_points(state, level.points)
                evaluated, work = evaluated + points, work + samples
            ratio_terms = self._add_light_at(values, state, level.points)
            if ratio_terms is not None:
                columns.append(ratio_terms)
        return level, torch.cat(columns, dim=1) if len(columns) > 1 else values, evaluated, work

    def coarse_image(self, level: Level, values: torch.Tensor) -> torch.Tensor:
        """(H, W, 3) the exact image of the unchanged lights plus `coarse_values` upsampled,
        camera exposure applied. A light whose visibility will be filtered takes its unshadowed
        diffuse light upsampled times the ratio of its upsampled sums of w V and w: the ratio
        estimator (Heitz et al. 2018) with the upsampling as the filter, where each point's own
        ratio (one light sample at matte points) would show as blotches."""
        upsampled = level.upsampler(values)  # at the level's pixel blocks (`Level.block`)
        coarse = upsampled[:, :3]
        for first in range(3, upsampled.shape[1], 5):
            unshadowed, sums = upsampled[:, first : first + 3], upsampled[:, first + 3 : first + 5]
            visible = torch.where(sums[:, 1] > 0, sums[:, 0] / sums[:, 1].clamp(min=1e-30), 0.0)
            coarse = coarse + unshadowed * visible.unsqueeze(-1)
        return level.add_to(self._static_image(self._changed()), coarse * self.exposure_scale)

    def _changed(self) -> list[_LightState]:
        """The lights set since the last exact frame."""
        return [state for state in self._lights.values() if state.edited > self._exact_edits]

    def _level(self, stride: int) -> Level:
        if stride not in self._levels:
            self._levels[stride] = build_level(self.gbuffer, self.supersampling, stride)
        return self._levels[stride]

    def _progress(self, state: _LightState) -> _Progress:
        """The light's images made so far; started again when their source changed (the memory
        budget dropped the transport they were shaded from)."""
        traced = state.transports is None
        if state.progress is None or state.progress.traced != traced:
            g = self.gbuffer
            done = torch.zeros(g.num_samples, dtype=torch.bool, device=g.device)
            groups = self._sample_groups(self._transport_light(state))
            samples = sum((g.num_samples if p is None else p.shape[0]) * num for p, num, _ in groups)
            per_point = samples / max(g.num_samples, 1)
            state.progress = _Progress(g.position.new_empty(2, g.num_samples, 3), done, traced, per_point)
            if traced and self._transport_fits(state):
                state.progress.parts = [[] for _ in groups]
        return state.progress

    def _refine_points(self, state: _LightState, points: torch.Tensor | None) -> tuple[int, float]:
        """Shade the light at those of `points` ((M,) ascending; None: all) not done yet; once
        every point is, its unit images are complete. Returns (points shaded, their samples)."""
        progress = self._progress(state)
        todo = torch.nonzero(~progress.done).squeeze(-1) if points is None else points[~_take(progress.done, points)]
        if todo.numel():
            progress.images.index_fill_(1, todo, 0.0)  # unlit points get no values, only these zeros
            if progress.traced:
                progress.shadow_sums = self._traced_images(
                    state, todo, progress.images, progress.shadow_sums, progress.parts
                )
            else:
                assert state.transports is not None  # not traced: shaded from the kept transport
                for transport in state.transports:
                    part = transport.subset(todo)
                    assert part.points is not None  # a subset names its points
                    progress.images.index_add_(1, part.points, self._per_point(state.light, part))
            progress.done[todo] = True
            progress.num_done += int(todo.numel())
        if points is None or progress.num_done == progress.done.shape[0]:
            images = progress.images
            visibility = None
            if progress.shadow_sums is not None:  # as in _streamed_images
                visibility = self._filtered_visibility(progress.shadow_sums)
                images[0].mul_(visibility.unsqueeze(-1))
            if progress.parts is not None:  # the transport `_transports` would have made
                state.transports = [self._kept_transport(group) for group in progress.parts if group]
                if visibility is not None:
                    self._filter_visibility(state.transports, visibility)
            self.counters["visibility"] += int(progress.traced)
            self.counters["shading"] += 1
            state.images, state.progress = images.half() if self._half_images else images, None
            self._fit_budget(state)
        return int(todo.numel()), int(todo.numel()) * progress.samples_per_point

    def _add_light_at(self, values: torch.Tensor, state: _LightState, points: torch.Tensor) -> torch.Tensor | None:
        """values (M, 3) plus the light's image at shading points `points` (M,), from its unit
        images or, while they are made, from the points done. A light whose visibility will be
        filtered adds its specular light only and returns (M, 5): its unshadowed diffuse light
        and its sums of w V and w at the points (see `coarse_values`); None otherwise."""
        light = state.light
        scale = colour_scale(light)
        if not scale.any():
            return None
        sums = None
        if state.images is not None:
            unit = state.images.index_select(1, points).to(values.dtype)
        else:
            assert state.progress is not None, "a light without images is refined before it is shown"
            unit = state.progress.images.index_select(1, points)
            if state.progress.shadow_sums is not None:
                sums = _take(state.progress.shadow_sums, points)
        diffuse_scale, specular_scale = (
            torch.as_tensor(scale * lobe, device=values.device, dtype=values.dtype)
            for lobe in (light.diffuse, light.specular)
        )
        mask = self.light_mask(light)
        if mask is not None:
            diffuse_scale, specular_scale = diffuse_scale * _take(mask, points), specular_scale * _take(mask, points)
        values.addcmul_(unit[1], specular_scale)
        if sums is not None:
            return torch.cat((unit[0] * diffuse_scale, sums), dim=1)
        values.addcmul_(unit[0], diffuse_scale)
        return None

    def _static_image(self, changed: list[_LightState]) -> torch.Tensor:
        """(H, W, 3) exact image of the emission and every light not in `changed`, kept while
        those stay the same. When only the last light set changed, these are `_others`."""
        changed_ids = {id(state) for state in changed}
        shown = [(path, state) for path, state in self._lights.items() if id(state) not in changed_ids]
        key = self.unchanged_key()
        if self._static is not None and self._static[0] == key:
            return self._static[1]
        only_active = len(changed) == 1 and changed[0] is self._lights.get(self._active or "")
        if only_active and self._others is not None:
            samples = self._others
        else:
            samples = self.gbuffer.params.emissive_color.clone()
            if self._folded is not None:  # folded lights are never changed ones (set_light unfolds)
                samples += self._folded
            for _, state in shown:
                if not state.folded:
                    self._add_light(samples, state)
            if only_active:
                self._others = samples
        self._static = (key, self.to_image(samples))
        return self._static[1]

    def _add_light(self, total: torch.Tensor, state: _LightState, in_place: bool = True) -> torch.Tensor:
        """total (N, 3) plus the light's image: its diffuse and specular images times their scales."""
        light = state.light
        scale = colour_scale(light)
        if not scale.any():
            return total if in_place else total.clone()
        diffuse, specular = self._images(state)
        diffuse_scale, specular_scale = (
            torch.as_tensor(scale * lobe, device=total.device, dtype=total.dtype)
            for lobe in (light.diffuse, light.specular)
        )
        mask = self.light_mask(light)
        if mask is not None:
            diffuse_scale, specular_scale = diffuse_scale * mask, specular_scale * mask
        # Without a mask the (3,) scales broadcast along rows of 3: read (N, 3) as rows of k
        # pixels and the scales tiled k times, so that torch's CPU kernels stream long rows.
        k = math.gcd(total.shape[0], _TILE_PIXELS) if mask is None else 1
        shape = (-1, 3 * k)
        if k > 1:
            diffuse, specular = diffuse.reshape(shape), specular.reshape(shape)
            diffuse_scale, specular_scale = diffuse_scale.repeat(k), specular_scale.repeat(k)
        rows = total.view(shape)
        rows = rows.addcmul_(diffuse, diffuse_scale) if in_place else torch.addcmul(rows, diffuse, diffuse_scale)
        return rows.addcmul_(specular, specular_scale).view(total.shape)

    # -- per-light stages -----------------------------------------------------------------------

    def light_mask(self, light: Light) -> torch.Tensor | None:
        """(N, 1) 1 where the light's light link includes the sample's object, 0 elsewhere; None
        when it links every object. Cached per distinct link."""
        link = light.light_link
        if link is None:
            return None
        if link not in self._masks:
            if self.object_paths is None:
                raise ValueError(
                    f"{light.path}: light linking needs the cache's object paths (re-bake the cache with this version)"
                )
            g = self.gbuffer
            self._masks[link] = linked_points(self.object_paths, link, g.object_id).to(g.position.dtype).unsqueeze(-1)
            self.counters["masks"] += 1
        return self._masks[link]

    def _chunks(self, num_samples: int, points: torch.Tensor | None, pieces: int = 1) -> list[slice | torch.Tensor]:
        """Consecutive chunks of all shading points (slices) or of `points` (index tensors), at
        least `pieces` of them (where there are enough points)."""
        n = self.gbuffer.num_samples if points is None else points.shape[0]
        step = max(1, min(self.settings.chunk_samples // num_samples, -(-n // pieces)))
        if points is not None:
            return [points[i : i + step] for i in range(0, n, step)] or [points]
        # No covered point (a camera that sees only sky) is one empty chunk: an empty transport.
        return [slice(i, min(i + step, n)) for i in range(0, n, step)] or [slice(0, 0)]

    def _sample_groups(self, light: Light) -> list[tuple[torch.Tensor | None, int, bool]]:
        """(points or None for all, samples per point, shared) of each group the light's
        transport is made in: a light whose visibility is filtered takes `filtered_area_samples`
        at matte points, evaluated once per pixel group where `RelightSettings.shared_lighting`
        (shared), and its usual count at glossy ones (`RelightSettings.filtered_area_samples`)."""
        samples = self.num_light_samples(light)
        if self.filter_radius == 0 or self._all_glossy or not has_closed_form(light):
            return [(None, samples, False)]
        few, shared = self.settings.filtered_area_samples, self._groups is not None and _scalar_radiance(light)
        if self._glossy_split is None:
            return [(None, few, shared)]
        matte, glossy = self._glossy_split
        return [(matte, few, shared), (glossy, samples, False)]

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

    def fixed_samples(self, num_samples: int) -> torch.Tensor:
        """(N, S, 2) the fixed light-sample numbers of every point for S samples, made once per S."""
        if num_samples not in self._u:
            g = self.gbuffer
            self._u[num_samples] = fixed_light_samples(
                g.num_samples, num_samples, self.settings.seed, g.device, g.position.dtype
            )
        return self._u[num_samples]

    def _transports(self, state: _LightState) -> list[Transport]:
        """Light samples, shadow rays and BRDF of the unshaped unit light at the points it reaches,
        one transport per sample group (`_sample_groups`)."""
        if state.transports is not None:
            return state.transports
        light = self._transport_light(state)
        state.transports = []
        # Tiles of points on threads of their own on the CPU (`relight_torch.parallel`).
        threads = tile_threads(self.gbuffer.device, self.visibility.thread_safe)
        for points, num_samples, shared in self._sample_groups(light):
            chunks = self._chunks(num_samples, points, threads)
            # Made here, shared by the tiles.
            shade = functools.partial(self._chunk_transport, light, points=self._points(num_samples, shared))
            parts = parallel_map(shade, chunks, threads)
            state.transports.append(parts[0] if len(parts) == 1 else self._joined(parts, chunks))
        if state.transports[0].shadow_sums is not None:
            self._filter_visibility(state.transports)
        state.images = None
        self.counters["visibility"] += 1
        return state.transports

    def _transport_light(self, state: _LightState) -> Light:
        """The unshaped unit light whose transport is cached (shaping and colour apply later)."""
        light = dataclasses.replace(unit_light(state.light), shaping=None, barzel=None)
        if light.shadow_link is not None and not isinstance(self.visibility, RayVisibility):
            raise ValueError(f"{light.path}: shadow linking needs Embree shadow rays (shadows='embree')")
        return light

    def _view_directions(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(N, 3) unit world directions E to the viewer, (N,) N.E and (N,) 1 / |N| of the shading
        normals N (stored in half precision: |N| = 1 to ~5e-4), made on first use: a Relighter
        handed its unit images (the multiview relighter's) never reads them.

        The BRDF takes N.E and N.L of the unit normal: with E, L and N unit in one space, N.h
        never exceeds |h|, which a sharp lobe's peak would otherwise see."""
        if self._viewer is None:
            self._viewer = _viewer_of(self.gbuffer)
        return self._viewer

    def _kept_transport(self, group: list[tuple[torch.Tensor, Transport]]) -> Transport:
        """One sample group's transport from the parts traced for its points, point by point
        (`_Progress.parts`): joined as `_transports` joins its tiles, its points ascending."""
        chunks: list[slice | torch.Tensor] = [chunk for chunk, _ in group]
        transport = self._joined([part for _, part in group], chunks)
        if transport.points is None:
            return transport
        order = torch.argsort(transport.points)
        subset = dataclasses.replace(transport, points=None).subset(order)
        return dataclasses.replace(
            subset, points=transport.points[order], shadow_sums=_reorder(transport.shadow_sums, order)
        )

    def _joined(self, parts: list[Transport], chunks: list[slice | torch.Tensor]) -> Transport:
        """One transport from the transports of consecutive chunks of shading points.

        Sparse parts keep their point lists; when the points reached are over half of all, every
        tensor is scattered to all N points (zeros elsewhere, ratio 1) and the list dropped.
        """
        n = self.gbuffer.num_samples

        def reached(chunk: slice | torch.Tensor, part: Transport) -> torch.Tensor:
            if part.points is not None:
                return part.points
            assert isinstance(chunk, slice), "only a transport of a slice of all points drops its point list"
            return torch.arange(chunk.start, chunk.stop, device=self.gbuffer.device)

        points = None
        if any(part.points is not None for part in parts):
            points = torch.cat([reached(chunk, part) for chunk, part in zip(chunks, parts, strict=True)])
        dense_points = points if points is not None and 2 * points.shape[0] > n else None
        dense = dense_points is not None

        def join(name: str, dim: int, fill: float) -> torch.Tensor | None:
            values = [getattr(part, name) for part in parts]
            if values[0] is None:
                return None
            joined = torch.cat(values, dim=dim)
            if dense_points is not None:
                shape = list(joined.shape)
                shape[dim] = n
                joined = joined.new_full(shape, fill).index_copy_(dim, dense_points, joined)
            return joined

        return Transport(
            None if dense else points,
            join("directions", 1, 0.0),
            join("lobes", 2, 0.0),
            join("diffuse_ratio", 0, 1.0),
            join("factors", 2, 0.0),
            parts[0].colour,
            join("shadow_sums", 0, 0.0),
        )

    def _filter_visibility(self, transports: list[Transport], visibility: torch.Tensor | None = None) -> None:
        """Fold the filtered visibility F(sum w V) / F(sum w) into the transports' diffuse ratios
        (Heitz et al. 2018; `visibility.surface_filter`) and drop the sums. The groups' sums
        are filtered together: each sum is already its group's mean over its samples. A
        `visibility` (N,) already filtered from the same sums is used as it is."""
        if visibility is None:
            g = self.gbuffer
            sums = g.position.new_zeros(g.num_samples, 2)
            for transport in transports:
                assert transport.shadow_sums is not None, "every transport of a filtered light keeps its sums"
                if transport.points is None:
                    sums += transport.shadow_sums
                else:  # the groups' points are disjoint (see _images)
                    sums.index_copy_(0, transport.points, transport.shadow_sums)
            visibility = self._filtered_visibility(sums)
        for transport in transports:
            points = transport.points
            assert transport.diffuse_ratio is not None, "a filtered light has a closed form, hence ratios"
            transport.diffuse_ratio = transport.diffuse_ratio * (
                visibility if points is None else _take(visibility, points)
            )
            transport.shadow_sums = None

    def _filtered_visibility(self, sums: torch.Tensor) -> torch.Tensor:
        """(N,) filtered visibility F(sum w V) / F(sum w) of per-point (N, 2) sums (0 where unlit),
        filtered only near shadows (`SurfaceFilter.visibility`): the filter's weights are made once,
        and a moved light pays only for the tiles its shadows' edges cross."""
        if self._groups is None:
            if self._surface_filter is None:
                self._surface_filter = SurfaceFilter(self.gbuffer, self.filter_radius)
            return self._surface_filter.visibility(sums)
        if self._surface_filter is None:  # on the pixel grid: the radius in pixels
            radius = max(1, self.filter_radius // self.supersampling)
            self._surface_filter = SurfaceFilter(self._groups.grid, radius)
        return self._groups.visibility(sums, self._surface_filter)

    def _points(self, num_samples: int, shared: bool) -> _Points:
        """The points a sample group's transport is evaluated at (`_chunk_transport`), `num_samples`
        fixed light samples each: every shading point, or with `shared` the pixel groups (their
        owners' samples), made once."""
        u = self.fixed_samples(num_samples)
        if not shared:
            return _Points(self.gbuffer, u, self._view_directions())
        groups = self._groups
        assert groups is not None, "shared transports come with pixel groups"
        if num_samples not in self._group_points:
            owned = u.index_select(0, groups.owners)
            self._group_points[num_samples] = _Points(groups.gbuffer, owned, _viewer_of(groups.gbuffer), groups)
        return self._group_points[num_samples]

    def _chunk_transport(self, light: Light, chunk: slice | torch.Tensor, points: _Points) -> Transport:
        """The transport of an unshaped unit light at the shading points of `chunk` (a slice of
        all of them, or their indices), evaluated at `points`: at each shading point, or once per
        pixel group at its centroid (`points.groups`, `direct.sharing`) and taken by each of the
        group's points (the materials' colours enter per point later, `_combined`)."""
        groups = points.groups
        if groups is None:
            return self._point_transport(light, chunk, points)
        rows, which = groups.of(chunk)
        transport = self._point_transport(light, rows, points)
        whole = None if isinstance(chunk, slice) else chunk
        if transport.points is None or (not isinstance(rows, slice) and transport.points.shape == rows.shape):
            return transport.gathered(which, whole)  # every group kept, in order
        where, held = transport.locate(_take(groups.rank, chunk))
        if bool(held.all()):
            return transport.gathered(where, whole)
        indices = torch.arange(chunk.start, chunk.stop, device=which.device) if isinstance(chunk, slice) else chunk
        return transport.gathered(where[held], indices[held])

    def _point_transport(self, light: Light, chunk: slice | torch.Tensor, at: _Points) -> Transport:
        """The transport of an unshaped unit light evaluated at each of the points `at` in `chunk`
        (a slice of them, or their indices).

        Points that no sample can light (facing away, inside the light, outside its cone of
        directions) cast no shadow rays and are dropped, unless they are fewer than half the
        chunk: then the whole chunk is kept, its rows read as views rather than gathered.
        Everything runs samples first, (S, P, ...): per-point values broadcast over whole slabs.
        """
        g, u, viewer = at.gbuffer, at.samples, at.viewer
        num_samples = u.shape[1]
        sample = sample_light(light, _take(g.position, chunk), _take(u, chunk))
        direction = sample.direction.transpose(0, 1)  # (S, C, 3), contiguous: see sample_light
        cosine = dot(direction, _take(g.normal, chunk))  # N.L at the shading normal as stored: the closed form's
        facing = dot(direction, _take(g.geometric_normal, chunk)) > 0
        # Every per-sample scalar in one (S, C) factor: 1 / pdf, both hemispheres, cos / S.
        scalar = sample.inverse_pdf().transpose(0, 1) * ((cosine > 0) & facing) * (cosine / num_samples)
        radiance = sample.radiance.transpose(0, 1)
        lit = ((scalar != 0) & (radiance != 0).any(-1)).any(0)
        exact = closed_form(light, _take(g.position, chunk), _take(g.normal, chunk))
        filtered = exact is not None and self.filter_radius > 0
        if filtered:  # lit by the closed form even where no sample is (see `uncovered` below)
            assert exact is not None  # filtered implies a closed form
            lit |= exact > 0
        wo, cos_e, inverse_norm = viewer
        lit &= _take(cos_e, chunk) > 0
        local: slice | torch.Tensor
        rows: slice | torch.Tensor
        points: torch.Tensor | None
        if 2 * int(lit.sum()) > lit.shape[0]:
            local, rows, points = slice(None), chunk, None if isinstance(chunk, slice) else chunk
        else:
            local = torch.nonzero(lit).squeeze(-1)
            rows = points = local + chunk.start if isinstance(chunk, slice) else chunk[local]
        direction, cosine = direction[:, local], cosine[:, local]
        scalar, radiance = scalar[:, local], radiance[:, local]
        distance = self.visibility.occluder_distance(
            light,
            _take(g.position, rows),
            _take(g.geometric_normal, rows),
            direction.transpose(0, 1),
            sample.distance.transpose(0, 1)[:, local].transpose(0, 1),
        )
        distance = distance.transpose(0, 1)
        # The samples' unshadowed estimate of the cosine-weighted solid angle, for the ratio estimator.
        reaching = (sample.distance < math.inf).transpose(0, 1)[:, local]
        ratio = None if exact is None else ratio_of(_take(exact, local), (scalar * reaching).sum(0))
        params, wo, shadow = g.params.index(rows), _take(wo, rows), light.shadow
        scale = light_radiance_scale(light)
        if _scalar_radiance(light):
            # L_i V = colour x scalar: keep per-sample scalars, not (S, P, 3) colours.
            k = int(np.argmax(np.abs(scale)))
            unshadowed = scalar * radiance[..., k] / float(scale[k])
            weight = unshadowed
            if shadow.enable:
                weight = weight * (
                    1.0 - (1.0 - shadow.color[0]) * shadow_strength(shadow, distance < math.inf, distance)
                )
            factors = preview_surface.split_factors(
                params, _take(cos_e, rows), cosine * _take(inverse_norm, rows), dot(direction, wo), self._coat
            )
            # With a filtered visibility the diffuse factors stay unshadowed (see Transport).
            factors[:2] *= unshadowed if filtered else weight
            factors[2:] *= weight
            sums = None
            if filtered:
                assert exact is not None  # filtered implies a closed form
                sums = torch.stack((weight.sum(0), unshadowed.sum(0)), dim=-1)
                # Points whose samples all fall below their horizon (a tangent plane cutting the
                # light) take the closed form as their unshadowed diffuse sum (Fresnel's s taken
                # as 0) and their visibility from the filter's neighbours.
                uncovered = torch.nonzero((sums[:, 1] == 0) & (_take(exact, local) > 0)).squeeze(-1)
                factors[0, 0, uncovered] = _take(exact, local)[uncovered]
            colour = torch.as_tensor(scale, device=factors.device, dtype=factors.dtype)
            if light.kind not in _SHAPED_KINDS:
                return Transport(points, None, None, ratio, factors.sum(1, keepdim=True), colour, sums)
            return Transport(points, direction, None, ratio, factors, colour, sums)
        weight = radiance * scalar.unsqueeze(-1)
        if shadow.enable:
            weight = weight * shadow_factor(shadow, distance < math.inf, distance)
        frame = (_take(g.tangent, rows), _take(g.bitangent, rows), _take(g.normal, rows))
        diffuse, specular = preview_surface.split(params, to_local(wo, *frame), to_local(direction, *frame))
        lobes = weight.new_empty(2, *weight.shape)
        torch.mul(diffuse, weight, out=lobes[0])
        torch.mul(specular, weight, out=lobes[1])
        if light.kind not in _SHAPED_KINDS:
            return Transport(points, None, lobes.sum(1, keepdim=True), ratio)
        return Transport(points, direction, lobes, ratio)

    def _images(self, state: _LightState) -> torch.Tensor:
        """The light's diffuse and specular unit images (2, N, 3): transport x shaping, per point."""
        if state.images is not None:
            return state.images
        if state.folded:  # made for this call only (light groups, a light's own image): not kept
            return self._streamed_images(state)
        if state.transports is None and not self._transport_fits(state):
            state.images = self._streamed_images(state)
            self._fit_budget(state)
            return state.images
        transports = self._transports(state)
        if len(transports) == 1 and transports[0].points is None:
            state.images = self._per_point(state.light, transports[0])
        else:  # groups of points: disjoint, so their sums land side by side
            state.images = self.gbuffer.position.new_zeros(2, self.gbuffer.num_samples, 3)
            for transport in transports:
                per_point = self._per_point(state.light, transport)
                if transport.points is None:
                    state.images += per_point
                else:  # copied, not added: 7 ms against 36 ms for 543,000 of 613,120 points
                    state.images.index_copy_(1, transport.points, per_point)
        self.counters["shading"] += 1
        if self._half_images:
            state.images = state.images.half()
        self._fit_budget(state)
        return state.images

    # -- memory budget ----------------------------------------------------------------------------

    def _transport_fits(self, state: _LightState) -> bool:
        """Whether the light's whole transport, kept, would leave the caches within the budget.

        Estimated from the kept layout (`Transport`): per point and sample up to six scalar
        factors and a direction, or two RGB lobes and a direction, in the G-buffer's dtype.
        """
        light = state.light
        size = self.gbuffer.position.element_size()
        per_sample = (6 + 3) * size if light.texture is None else (2 * 3 + 3) * size
        samples = max(num for _, num, _ in self._sample_groups(light))
        needed = self.gbuffer.num_samples * samples * per_sample
        kept = sum(
            other.images.numel() * other.images.element_size()
            for other in self._lights.values()
            if other.images is not None
        )
        return kept + needed <= self.memory_budget

    def _fit_budget(self, current: _LightState) -> None:
        """Bring `cache_bytes` towards the budget after `current`'s images were made: drop the
        transports of the lights edited longest ago, then `current`'s own (`_fold_to_budget`
        does the rest once the frame is made)."""
        # The lights edited longest ago first, the one just shaded last.
        others = sorted((state for state in self._lights.values() if state is not current), key=lambda s: s.edited)
        for state in others + [current]:
            if self.cache_bytes() <= self.memory_budget:
                return
            state.transports = None

    def _fold_to_budget(self) -> None:
        """After a frame, bring `cache_bytes` within the budget if dropping transports did not:
        fold the images of the lights edited longest ago into one sum (the frame stays the same;
        an edit of a folded light makes its images again, `_unfold`), never the active light's
        (its colour edits stay a rescale) nor images made elsewhere (`set_unit_images`); then keep
        every unit image in half precision. Run between frames: `_others` already holds them."""
        if self.cache_bytes() <= self.memory_budget:
            return
        for state in sorted(self._lights.values(), key=lambda s: s.edited):
            if self.cache_bytes() <= self.memory_budget:
                return
            if state.images is not None and not state.external and state.light.path != self._active:
                self._fold(state)
        if self.cache_bytes() > self.memory_budget and not self._half_images:
            self._half_images = True
            for state in self._lights.values():
                if state.images is not None:
                    state.images = state.images.half()

    def _fold(self, state: _LightState) -> None:
        """Add the light's image (colour, lobe multipliers and light link applied) to `_folded`
        and drop its images and transport."""
        if self._folded is None:
            self._folded = torch.zeros_like(self.gbuffer.position)
        self._add_light(self._folded, state)
        state.images, state.transports, state.progress, state.folded = None, None, None, True

    def _unfold(self, state: _LightState) -> None:
        """Before a folded light changes: make its images again (traced tile by tile, the same
        numbers as before: fixed samples) and take its image out of `_folded`."""
        assert self._folded is not None, "a folded light's image is in the folded sum"
        state.folded = False
        state.images = self._streamed_images(state)
        image = self._add_light(torch.zeros_like(self._folded), state)
        self._folded.sub_(image)
        self._others = None
        self._static = None

    def _streamed_images(self, state: _LightState) -> torch.Tensor:
        """The light's unit images (2, N, 3) made tile by tile, each tile's transport dropped once
        shaded: what a light costs when its transport does not fit the budget (a later shaping
        edit traces it again). The same numbers as `_transports` then `_images`."""
        g = self.gbuffer
        images = g.position.new_zeros(2, g.num_samples, 3)
        sums = self._traced_images(state, None, images, None)
        if sums is not None:  # the filtered visibility multiplies the diffuse image (see _filter_visibility)
            images[0].mul_(self._filtered_visibility(sums).unsqueeze(-1))
        self.counters["visibility"] += 1
        self.counters["shading"] += 1
        return images.half() if self._half_images else images

    def _traced_images(
        self,
        state: _LightState,
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
        light = self._transport_light(state)
        g = self.gbuffer
        threads = tile_threads(g.device, self.visibility.thread_safe)
        for group, (points, num_samples, shared) in enumerate(self._sample_groups(light)):
            if todo is not None:
                if points is not None:  # the group's points among `todo`
                    member = torch.zeros(g.num_samples, dtype=torch.bool, device=g.device)
                    member[points] = True
                    points = todo[member[todo]]
                else:
                    points = todo
                if points.numel() == 0:
                    continue
            chunks = self._chunks(num_samples, points, threads)
            shading = self._points(num_samples, shared)

            def tile(
                chunk: slice | torch.Tensor,
                shading: _Points = shading,
            ) -> tuple[torch.Tensor, torch.Tensor, Transport]:
                part = self._chunk_transport(light, chunk, shading)
                if part.points is None:  # the whole tile: name its points, as `_joined` does
                    part.points = (
                        torch.arange(chunk.start, chunk.stop, device=g.device) if isinstance(chunk, slice) else chunk
                    )
                return part.points, self._per_point(state.light, part), part

            for (index, per_point, part), chunk in zip(parallel_map(tile, chunks, threads), chunks, strict=True):
                images.index_add_(1, index, per_point)
                shadow_sums = part.shadow_sums
                if parts is not None:
                    assert isinstance(chunk, torch.Tensor), "parts are kept of point lists (progressive refinement)"
                    parts[group].append((chunk, part))
                if shadow_sums is not None:
                    sums = g.position.new_zeros(g.num_samples, 2) if sums is None else sums
                    sums.index_add_(0, index, shadow_sums)
        return sums

    def _per_point(self, light: Light, transport: Transport) -> torch.Tensor:
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
        if self._factor_colours is None:
            self._factor_colours = preview_surface.factor_colours(self.gbuffer.params, self._coat)
        colours = self._factor_colours
        if transport.points is not None:
            colours = colours.index_select(1, transport.points)
        return torch.stack(preview_surface.combine_factors(colours, sums)).mul_(transport.colour)

    def _emission_factor(self, light: Light, transport: Transport) -> torch.Tensor | None:
        """(S, P, 3) ShapingAPI x Barzel factor of each cached sample; None when nothing applies."""
        if not transport.shapeable or (light.shaping is None and light.barzel is None):
            return None
        position = self.gbuffer.position
        if light.barzel is not None and transport.points is not None:  # receivers matter to Barzel only
            position = _take(position, transport.points)
        origin = torch.as_tensor(light.world_from_light[:3, 3], device=position.device, dtype=position.dtype)
        return emission_factor(light, transport.emission_in(light), position, origin)


class _Points(NamedTuple):
    """Where a transport is evaluated: the points of `gbuffer`, their fixed light samples (N, S, 2),
    their `_viewer_of` terms, and the pixel groups they stand for (None: the shading points themselves)."""

    gbuffer: GBuffer
    samples: torch.Tensor
    viewer: tuple[torch.Tensor, torch.Tensor, torch.Tensor]
    groups: PixelGroups | None = None


def _viewer_of(g: GBuffer) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(N, 3) unit directions E from the points of `g` to the camera, (N,) N.E and (N,) 1 / |N| of
    their shading normals N (`Relighter._view_directions`)."""
    wo, normal = g.wo_world(), g.normal
    inverse_norm = dot(normal, normal).rsqrt_()
    return wo, dot(wo, normal).mul_(inverse_norm), inverse_norm


def _scalar_radiance(light: Light) -> bool:
    """Whether the unit light's shadowed radiance L_i V is one colour times a scalar (untextured,
    grey shadow colour): its transport is then kept as scalar factors (`Transport.factors`)."""
    return light.texture is None and bool(light_radiance_scale(light).any()) and len(set(light.shadow.color)) == 1


def embree_visibility(
    occluders: np.ndarray,
    occluder_objects: np.ndarray | None,
    object_paths: list[str] | None,
    opacity: OpacityTable | None = None,
) -> tuple[EmbreeCaster, RayVisibility]:
    """Embree over a cache's (T, 3, 3) occluders and the shadow-ray visibility using it, with a
    caster per shadow-link set when the (T,) occluder objects and their paths are given; shadow
    rays pass through the holes of the occluders' `opacity` table (`load_opacity`)."""
    caster = EmbreeCaster(occluders, opacity=opacity)
    links = None
    if occluder_objects is not None:
        assert object_paths is not None, "occluder objects come with the paths they index"
        links = ShadowLinkCasters(occluders, occluder_objects, object_paths, caster.epsilon, opacity=opacity)
    return caster, RayVisibility(caster, links)


def load_opacity(layer_path: Path, description: CacheDescription) -> OpacityTable | None:
    """The occluders' opacity table of a cache (`OpacityTable.to_arrays` payloads), None when the
    bake found every occluder opaque (and wrote none)."""
    names = {payload.name for payload in description.payloads}
    if OPACITY_PAYLOADS[0] not in names:
        return None
    try:
        return OpacityTable.from_arrays({name: load_npy(layer_path, description, name) for name in OPACITY_PAYLOADS})
    except (KeyError, ValueError) as error:
        raise RelightError(f"{layer_path}: occluder opacity payloads: {error}") from error


def open_relighter(
    path: str | os.PathLike[str],
    device: str | torch.device = "cpu",
    shadows: str = "embree",
    lights_layer: str | os.PathLike[str] | None = None,
    settings: RelightSettings = RelightSettings(),
) -> Relighter:
    """A Relighter for a cache layer, with the shot's lights (and `lights_layer`'s edits over them).

    Everything is checked before tensors are allocated (`relight_torch.cache.load`): payload sizes
    and hashes, headers against the layer, and the inputs the bake read (a stale cache is refused).

    Args:
        path: `<stem>.relight.usda`.
        device: torch device of the relighting kernels.
        shadows: 'embree' (exact shadow rays, CPU) or 'shadowmaps' (torch, any device).
        lights_layer: USD layer of light edits composed over the shot's lights.
        settings: sampling settings.
    """
    layer_path = Path(path)
    description = read_cache_layer(layer_path)
    check_inputs(layer_path, description)
    gbuffer = load_gbuffer(layer_path, description).to(device)
    # Mapped read-only, not loaded: Embree copies it block by block and gives its pages back.
    occluders = load_npy(layer_path, description, "occluders")
    linking = {payload.name for payload in description.payloads} >= {"objectPaths", "occluderObjects"}
    object_paths = decode_paths(load_npy(layer_path, description, "objectPaths")) if linking else None
    visibility: Visibility
    if shadows == "embree":
        occluder_objects = np.asarray(load_npy(layer_path, description, "occluderObjects")) if linking else None
        _, visibility = embree_visibility(
            occluders, occluder_objects, object_paths, load_opacity(layer_path, description)
        )
    elif shadows == "shadowmaps":
        # Always cube maps for spot lights: a cone edit does not re-run visibility, and a perspective
        # map sized for the old cone would leave the new one's receivers unshadowed.
        visibility = ShadowMapVisibility(
            torch.from_numpy(np.array(occluders)).to(device),  # writable: torch keeps a reference
            settings.shadow_map_resolution,
            settings.shadow_map_march_steps,
            receivers=gbuffer.position,
            max_spot_half_angle=0.0,
            lookup=settings.shadow_map_lookup,
            opacity=load_opacity(layer_path, description),
        )
    else:
        raise RelightError(f"shadows must be 'embree' or 'shadowmaps', got {shadows!r}")
    relighter = Relighter(
        gbuffer, visibility, description.supersampling, description.exposure_scale, settings, object_paths
    )
    relighter.description = description
    relighter.set_lights(shot_lights(description, lights_layer))
    return relighter


def shot_lights(description: CacheDescription, lights_layer: str | os.PathLike[str] | None = None) -> list[Light]:
    """The lights of the cache's shot, at the baked time, with `lights_layer` composed over them.

    Raises:
        RelightError: a file cannot be opened, or a light has a bad value (naming prim and attribute).
    """
    stage = open_stage(description.source, lights_layer)
    shot = os.fspath(lights_layer or description.source)
    check_composition(stage, shot)
    for line in outside_reads(description.source, lights_layer) if lights_layer is not None else []:
        logging.getLogger("relight").warning(line)
    time = description.parameters.get("time")
    try:
        return read_stage_lights(stage, time_code(stage, None if time is None else float(time)))
    except ValueError as error:
        raise RelightError(f"{defining_layer(stage, str(error), shot)}: {error}") from None
