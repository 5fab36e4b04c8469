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
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.cache.layer import CacheDescription, read_cache_layer
from relight_torch.cache.load import check_inputs, load_gbuffer, load_npy
from relight_torch.direct import gradients
from relight_torch.direct.budget import MemoryBudget
from relight_torch.direct.gradients import GEOMETRY_KINDS
from relight_torch.direct.images import add_scaled, box_filter, lobe_scales
from relight_torch.direct.loading import embree_visibility, load_opacity, shot_lights
from relight_torch.direct.progressive import Progress, add_light_at, coarse_light, refine_points, reshade_at
from relight_torch.direct.rig import LightState, light_group, light_keys, replace_rig
from relight_torch.direct.settings import RelightSettings, auto_filter_radius, default_memory_budget
from relight_torch.direct.stages import LightStages
from relight_torch.direct.transport import Transport
from relight_torch.errors import RelightError
from relight_torch.gbuffer import GBuffer
from relight_torch.levels import Level, build_level
from relight_torch.lights.emission import validate_light
from relight_torch.lights.light import Light, LightKind, lights_equal
from relight_torch.lights.linking import decode_paths, linked_points
from relight_torch.material_edits import MaterialChange, apply_material_edit
from relight_torch.protocol import Refinement
from relight_torch.visibility import Visibility
from relight_torch.visibility.shadow_maps import ShadowMapVisibility


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
        material_paths: the prim path of each material id, to edit materials by path
            (`edit_material`); None when unknown (a cache baked before it was stored).

    Attributes:
        description: the cache layer's description when opened with `open_relighter`.
        counters: 'visibility', 'shading' and 'masks' passes run so far (one per light and stage).
    """

    material_edits = True  # `edit_material` shades the edited materials' points again (`CacheRelighter`)
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
        material_paths: list[str] | None = None,
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
        self.material_paths = material_paths
        self._baked_params = gbuffer.params  # what `set_material_edits` edits
        self._lights: dict[str, LightState] = {}
        self._masks: dict[tuple[str, ...], torch.Tensor] = {}
        self._stages = LightStages(gbuffer, visibility, settings, self.filter_radius, supersampling, self.counters)
        # Every pixel covered in order: scattering into the image is a reshape.
        self._dense = gbuffer.num_samples == height * width and bool(
            (gbuffer.pixel_index == torch.arange(height * width, device=gbuffer.device)).all()
        )
        # Emission plus every light but `_active` (the last one edited), or None when stale.
        self._active: str | None = None
        self._others: torch.Tensor | None = None
        self._budget = MemoryBudget(
            default_memory_budget() if settings.memory_budget is None else settings.memory_budget
        )
        # Counts changes of the rig: each light's last one orders what the budget drops, and the
        # lights changed after the last exact frame (`_exact_edits`) are those a coarse frame refines.
        self._edits = 0
        self._exact_edits = 0
        self._levels: dict[int, Level] = {}  # progressive refinement's coarse levels, by stride
        # (key, (H, W, 3) image) of the lights a coarse frame shows exactly (`_static_image`).
        self._static: tuple[object, torch.Tensor] | None = None

    @property
    def memory_budget(self) -> int:
        """Bytes the per-light caches may hold between renders (`RelightSettings.memory_budget`)."""
        return self._budget.limit

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
        transport_key, shading_key = light_keys(light)
        state = self._lights.get(light.path)
        if state is not None and lights_equal(state.light, light):
            return  # no change: nothing to redo, nothing for progressive refinement to refine
        if state is not None and state.folded:
            self._unfold(state)
        if state is None or state.geometry_key != transport_key:
            state = LightState(light, transport_key, shading_key)
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
        return self._budget.held_bytes(self._lights.values())

    def held_bytes(self) -> int:
        """`CacheRelighter.held_bytes`: the per-light caches (`cache_bytes`)."""
        return self.cache_bytes()

    def edit_material(self, material: int | str, **values: object) -> None:
        """`CacheRelighter.edit_material`: set UsdPreviewSurface inputs (constants) of one material,
        by id or prim path, e.g. `edit_material("/World/Looks/Wall", diffuse_color=(0.1, 0.5, 0.1),
        roughness=0.6)` (`set_params`).

        Raises:
            RelightError: a bad material or input (`material_edits.apply_material_edit`), or as
                `set_params`.
        """
        g = self.gbuffer
        params, rows = apply_material_edit(g.params, g.material_id, material, values, self.material_paths)
        self._change_params(params, MaterialChange(frozenset(values), rows))

    def set_material_edits(self, edits: Mapping[int | str, Mapping[str, object]]) -> None:
        """`CacheRelighter.set_material_edits`: the baked materials with `edits` (`set_params`)."""
        g, params = self.gbuffer, self._baked_params
        for material, values in edits.items():
            params, _ = apply_material_edit(params, g.material_id, material, values, self.material_paths)
        self.set_params(params)

    def set_params(self, params: PreviewSurfaceParams) -> None:
        """Replace the material parameters of every sub-sample (rows as the G-buffer's).

        Every light's work away from the changed points is kept. A change of colours only
        (`material_edits.COLOUR_INPUTS`) shades those points again from each light's kept
        transport where it keeps one of scalar factors, tracing nothing; any other change, and a
        dome (whose BRDF samples follow the material), traces the light again at the changed points
        only. A light whose transport is not kept, and every light after a change of which points
        are glossy or have a clearcoat (their samples per point), is traced again whole. An emissive
        colour change alters the emission alone. Progressive refinement sees the lights as edited
        (`edits`).

        Raises:
            RelightError: another number of rows, an opacity change (`MaterialChange.between`), or a
                light whose images were given from elsewhere (`set_unit_images`: not shaded here).
        """
        params = params.to(self.gbuffer.device, self.gbuffer.position.dtype)
        self._change_params(params, MaterialChange.between(self.gbuffer.params, params))

    def _change_params(self, params: PreviewSurfaceParams, change: MaterialChange) -> None:
        """`set_params` of `params` that differ from the current ones by `change` (or less)."""
        if not change.inputs or not bool(change.rows.any()):
            return
        external = [path for path, state in self._lights.items() if state.external]
        if external:
            raise RelightError(
                f"{external[0]}: its light was shaded elsewhere (set_unit_images); a material edit cannot "
                "shade it again"
            )
        for state in self._lights.values():
            if state.folded:  # out of the folded sum while it still holds the old materials' light
                self._unfold(state)
        old_stages = self._stages
        self._stages = old_stages.with_params(params, change)
        self.gbuffer = self._stages.gbuffer
        self._edits += 1
        self._others, self._static = None, None
        if change.inputs == {"emissive_color"}:
            return  # no light reflects differently
        same_groups = self._stages.same_sample_groups(old_stages)
        for state in self._lights.values():
            if same_groups and self._transport_serves(state, change):
                reshade_at(self._stages, state, change.rows)
            else:
                state.transports, state.images, state.progress, state.stale = None, None, None, None
            state.edited = self._edits

    def _transport_serves(self, state: LightState, change: MaterialChange) -> bool:
        """Whether the light's kept transport serves the changed materials: as it is for a change of
        colours of a transport of scalar factors (whose colours enter when its images are made; not
        a dome's, whose BRDF samples follow the colours too), or once its changed points are traced
        again, as they are shaded (`LightState.stale`, `LightStages.retrace_stale`)."""
        if state.transports is None:
            return False
        recolour = all(t.factors is not None for t in state.transports) and state.light.kind is not LightKind.DOME
        if change.colour_only and recolour:
            return True
        state.stale = change.rows.clone() if state.stale is None else state.stale | change.rows
        self.counters["visibility"] += 1
        return True

    def unit_images(self, path: str) -> torch.Tensor | None:
        """Light `path`'s cached diffuse and specular unit images (2, N, 3); None before it is shaded
        and after an edit of its transform or shaping dropped them (`set_light`)."""
        return self._lights[path].images

    def set_unit_images(self, path: str, images: torch.Tensor) -> None:
        """Give light `path` unit images (2, N, 3) computed elsewhere (the multiview relighter
        gathers them from its caching cameras): `render` then traces and shades nothing for it
        until an edit of its transform or shaping drops them. Counted as an edit of the light
        (`edits`): a progressive refinement under way starts again and its coarse frames show them."""
        state = self._lights[path]
        if state.folded:
            self._unfold(state)
        state.images, state.progress, state.external = images, None, True
        self._edits += 1
        state.edited = self._edits
        self._others = None

    # -- rendering ------------------------------------------------------------------------------

    def render_samples(self) -> torch.Tensor:
        """(N, 3) radiance of every covered sub-sample (camera exposure not applied)."""
        self._exact_edits = self._edits
        if self._others is None:
            self._others = self.gbuffer.params.emissive_color.clone()
            if self._budget.folded is not None:
                self._others += self._budget.folded
            for path, state in self._lights.items():
                if path != self._active and not state.folded:
                    self._add_light(self._others, state)
        if self._active not in self._lights:
            values = self._others.clone()
        else:
            values = self._add_light(self._others, self._lights[self._active], in_place=False)
        self._budget.fold_oldest(self._lights.values(), self._active, self.gbuffer.position, self._add_light)
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

    def _add_light(self, total: torch.Tensor, state: LightState, in_place: bool = True) -> torch.Tensor:
        """total (N, 3) plus the light's image: its diffuse and specular images times their scales."""
        scales = lobe_scales(state.light, total)
        if scales is None:
            return total if in_place else total.clone()
        diffuse, specular = self._images(state)
        return add_scaled(total, (diffuse, specular), scales, self.light_mask(state.light), in_place)

    # -- progressive refinement (`CacheRelighter.refine`, `relight_torch.progressive`) ----------

    @property
    def edits(self) -> int:
        """`CacheRelighter.edits`: light additions, edits and removals, and unit images given
        (`set_unit_images`), so far."""
        return self._edits

    def pending(self, stride: int | None) -> float:
        """`CacheRelighter.pending`: light samples still to evaluate for the changed lights at
        `stride` (points times their samples)."""
        points = None if stride is None else self._level(stride).points
        total = 0.0
        for state in self._changed():
            if state.images is None:
                total += self._progress(state).pending(points)
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
            ratio_terms = add_light_at(values, state, level.points, self.light_mask)
            if ratio_terms is not None:
                columns.append(ratio_terms)
        return level, torch.cat(columns, dim=1) if len(columns) > 1 else values, evaluated, work

    def coarse_image(self, level: Level, values: torch.Tensor) -> torch.Tensor:
        """(H, W, 3) the exact image of the unchanged lights plus `coarse_values` upsampled,
        camera exposure applied (a light whose visibility will be filtered by the ratio of its
        upsampled sums, `progressive.coarse_light`)."""
        coarse = coarse_light(level.upsampler(values))  # at the level's pixel blocks (`Level.block`)
        return level.add_to(self._static_image(self._changed()), coarse * self.exposure_scale)

    def _changed(self) -> list[LightState]:
        """The lights set since the last exact frame."""
        return [state for state in self._lights.values() if state.edited > self._exact_edits]

    def _level(self, stride: int) -> Level:
        if stride not in self._levels:
            self._levels[stride] = build_level(self.gbuffer, self.supersampling, stride)
        return self._levels[stride]

    def _progress(self, state: LightState) -> Progress:
        """The light's images made so far; started again when their source changed (the memory
        budget dropped the transport they were shaded from)."""
        traced = state.transports is None
        if state.progress is None or state.progress.traced != traced:
            groups = self._stages.sample_groups(self._stages.transport_light(state.light))
            state.progress = Progress.start(self.gbuffer, groups, traced, traced and self._transport_fits(state))
        return state.progress

    def _refine_points(self, state: LightState, points: torch.Tensor | None) -> tuple[int, float]:
        """Shade the light at those of `points` ((M,) ascending; None: all) not done yet; once
        every point is, its unit images are complete. Returns (points shaded, their samples)."""
        shaded, samples, images = refine_points(self._stages, state, self._progress(state), points)
        if images is not None:
            state.images, state.progress = self._budget.kept(images), None
            self._budget.drop_transports(self._lights.values(), state)
        return shaded, samples

    def _static_image(self, changed: list[LightState]) -> torch.Tensor:
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
            if self._budget.folded is not None:  # folded lights are never changed ones (set_light unfolds)
                samples += self._budget.folded
            for _, state in shown:
                if not state.folded:
                    self._add_light(samples, state)
            if only_active:
                self._others = samples
        self._static = (key, self.to_image(samples))
        return self._static[1]

    # -- per-light stages (`direct.stages`) -----------------------------------------------------

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

    def num_light_samples(self, light: Light) -> int:
        """Light samples per point the light gets without a visibility filter (`RelightSettings`)."""
        return self._stages.num_light_samples(light)

    def fixed_samples(self, num_samples: int) -> torch.Tensor:
        """(N, S, 2) the fixed light-sample numbers of every point for S samples, made once per S."""
        return self._stages.points.fixed_samples(num_samples)

    def _transports(self, state: LightState) -> list[Transport]:
        """The light's transport, one per sample group (`LightStages.transports`), made on first use."""
        if state.transports is None:
            state.transports = self._stages.transports(state.light)
            state.images, state.stale = None, None
        self._stages.retrace_stale(state)
        return state.transports

    def _images(self, state: LightState) -> torch.Tensor:
        """The light's diffuse and specular unit images (2, N, 3): transport x shaping, per point."""
        if state.images is not None:
            return state.images
        if state.folded:  # made for this call only (light groups, a light's own image): not kept
            return self._streamed_images(state)
        if state.transports is None and not self._transport_fits(state):
            state.images = self._streamed_images(state)
            self._budget.drop_transports(self._lights.values(), state)
            return state.images
        state.images = self._budget.kept(self._stages.images(state.light, self._transports(state)))
        self._budget.drop_transports(self._lights.values(), state)
        return state.images

    # -- memory budget (`direct.budget`) ----------------------------------------------------------

    def _transport_fits(self, state: LightState) -> bool:
        """Whether the light's whole transport, kept, would leave the caches within the budget."""
        return self._budget.transport_fits(self._lights.values(), self._stages.transport_bytes(state.light))

    def _streamed_images(self, state: LightState) -> torch.Tensor:
        """The light's unit images made tile by tile, its transport not kept (`LightStages.streamed_images`)."""
        return self._budget.kept(self._stages.streamed_images(state.light))

    def _unfold(self, state: LightState) -> None:
        """Before a folded light changes: make its images again (traced tile by tile, the same
        numbers as before: fixed samples) and take its image out of the folded sum."""
        self._budget.unfold(state, self._streamed_images(state), self._add_light)
        self._others = None
        self._static = None


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
    names = {payload.name for payload in description.payloads}
    linking = names >= {"objectPaths", "occluderObjects"}
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
    material_paths = (
        decode_paths(load_npy(layer_path, description, "materialPaths")) if "materialPaths" in names else None
    )
    relighter = Relighter(
        gbuffer,
        visibility,
        description.supersampling,
        description.exposure_scale,
        settings,
        object_paths,
        material_paths,
    )
    relighter.description = description
    relighter.set_lights(shot_lights(description, lights_layer))
    return relighter
