"""The relighter: direct light on a deep framebuffer, re-rendering only what an edit touches.

Light is linear, so the image is a sum over lights of colour_scale(light) x unit_image(light),
where colour_scale = intensity 2^exposure color [blackbody] and unit_image is the light's image
with those set to 1. Per light the relighter keeps three stages, each recomputed only when its
inputs change:

    samples + visibility   <- transform, size, kind, texture, shadow settings   (Visibility calls)
    unit_image             <- the above + shaping, Barzel controls, diffuse/specular multipliers
    colour_scale           <- intensity, exposure, color, colour temperature    (a multiply)

Area lights and domes use fixed stratified samples per shading point (`light_samples`), so the
image does not flicker while a light is edited. `counters` counts visibility and shading passes
(tests use it to check that a colour edit shades nothing).
"""

from __future__ import annotations

import collections
import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from relight_torch.cache.layer import CacheDescription, read_cache_layer
from relight_torch.cache.load import check_inputs, load_gbuffer, load_npy
from relight_torch.errors import RelightError
from relight_torch.gbuffer import GBuffer
from relight_torch.light_samples import fixed_light_samples
from relight_torch.lights.emission import LightSample, is_delta_light, light_radiance_scale, sample_light
from relight_torch.lights.light import Light, LightKind
from relight_torch.lights.shadow import shadow_factor
from relight_torch.lights.usd import read_stage_lights
from relight_torch.math.frame import to_local
from relight_torch.shading import reflected_radiance
from relight_torch.stage import open_stage, time_code
from relight_torch.visibility import Visibility
from relight_torch.visibility.embree import EmbreeCaster
from relight_torch.visibility.rays import RayVisibility


_COLOUR_FIELDS = ("intensity", "exposure", "color", "enable_color_temperature", "color_temperature")
_SHADING_FIELDS = ("shaping", "barzel", "diffuse", "specular")


@dataclass(frozen=True)
class RelightSettings:
    """Sampling of the relighter.

    Attributes:
        area_samples: fixed samples per shading point for sphere, rect, disk, cylinder and distant
            lights with an angle (delta lights take one).
        dome_samples: fixed samples per shading point for dome lights.
        seed: seed of the per-point sample rotations.
        chunk_points: shading points processed together (bounds the (N, S, 3) temporaries).
    """

    area_samples: int = 16
    dome_samples: int = 64
    seed: int = 0
    chunk_points: int = 1 << 16


def _key(light: Light, names: tuple[str, ...]) -> tuple:
    """A hashable snapshot of some fields of a light (arrays by content)."""
    values = []
    for name in names:
        value = getattr(light, name)
        if isinstance(value, np.ndarray):
            value = (value.shape, value.tobytes())
        values.append(value)
    return tuple(values)


def _geometry_fields() -> tuple[str, ...]:
    skip = set(_COLOUR_FIELDS) | set(_SHADING_FIELDS) | {"path", "light_group"}
    return tuple(f.name for f in dataclasses.fields(Light) if f.name not in skip)


_GEOMETRY_FIELDS = _geometry_fields()


def unit_light(light: Light) -> Light:
    """The light with intensity 1, exposure 0, white colour and no colour temperature."""
    return dataclasses.replace(light, intensity=1.0, exposure=0.0, color=(1.0, 1.0, 1.0),
                               enable_color_temperature=False)


def colour_scale(light: Light) -> np.ndarray:
    """(3,) factor turning the light's unit image into its image (see the module doc)."""
    unit = light_radiance_scale(unit_light(light))
    full = light_radiance_scale(light)
    return np.divide(full, unit, out=np.zeros(3), where=unit != 0)


@dataclass
class _LightState:
    light: Light
    geometry_key: tuple
    shading_key: tuple
    samples: list[LightSample]         # one per chunk of shading points
    shadow: list[torch.Tensor]         # (n, S, 3) shadow factor per chunk
    unit_image: torch.Tensor | None    # (N, 3)


class Relighter:
    """Direct relighting of one deep framebuffer.

    Args:
        gbuffer: the covered sub-samples (device and dtype of every computation).
        visibility: shadow queries (Embree rays or torch shadow maps).
        supersampling: s; the sub-sample image is box-filtered by s x s after shading.
        exposure_scale: the camera's linear exposure scale.
        settings: sampling settings.

    Attributes:
        description: the cache layer's description when opened with `open_relighter`.
    """

    def __init__(self, gbuffer: GBuffer, visibility: Visibility, supersampling: int = 1,
                 exposure_scale: float = 1.0, settings: RelightSettings = RelightSettings()):
        height, width = gbuffer.image_size
        if height % supersampling or width % supersampling:
            raise ValueError(f"image {width}x{height} is not a multiple of supersampling {supersampling}")
        self.gbuffer = gbuffer
        self.visibility = visibility
        self.supersampling = supersampling
        self.exposure_scale = exposure_scale
        self.settings = settings
        self.counters: collections.Counter[str] = collections.Counter()
        self.description: CacheDescription | None = None
        self._lights: dict[str, _LightState] = {}
        self._wo_local = to_local(gbuffer.wo_world(), gbuffer.tangent, gbuffer.bitangent, gbuffer.normal)
        self._u: dict[int, torch.Tensor] = {}

    # -- lights ---------------------------------------------------------------------------------

    @property
    def lights(self) -> list[Light]:
        return [state.light for state in self._lights.values()]

    def set_lights(self, lights: list[Light]) -> None:
        """Replace the whole rig; unchanged lights keep their cached work."""
        for path in set(self._lights) - {light.path for light in lights}:
            del self._lights[path]
        for light in lights:
            self.set_light(light)

    def set_light(self, light: Light) -> None:
        """Add a light or edit one (matched by path); invalidates only what the edit touches."""
        geometry_key = _key(light, _GEOMETRY_FIELDS)
        shading_key = geometry_key + _key(light, _SHADING_FIELDS)
        state = self._lights.get(light.path)
        if state is None or state.geometry_key != geometry_key:
            state = _LightState(light, geometry_key, shading_key, [], [], None)
        elif state.shading_key != shading_key:
            state.unit_image, state.shading_key = None, shading_key
        state.light = light
        self._lights[light.path] = state

    def remove_light(self, path: str) -> None:
        if path not in self._lights:
            raise KeyError(f"no light {path!r} in the relighter (has {sorted(self._lights)})")
        del self._lights[path]

    # -- rendering ------------------------------------------------------------------------------

    def render_samples(self) -> torch.Tensor:
        """(N, 3) radiance of every covered sub-sample (camera exposure not applied)."""
        total = self.gbuffer.params.emissive_color.clone()
        for state in self._lights.values():
            scale = torch.as_tensor(colour_scale(state.light), device=total.device, dtype=total.dtype)
            if bool((scale == 0).all()):
                continue
            total += scale * self._unit_image(state)
        return total

    def render(self) -> torch.Tensor:
        """(H, W, 3) linear image: sub-samples shaded, box-filtered, camera exposure applied."""
        image = self.gbuffer.scatter(self.render_samples())
        s = self.supersampling
        if s > 1:
            height, width, _ = image.shape
            image = image.reshape(height // s, s, width // s, s, 3).mean(dim=(1, 3))
        return image * self.exposure_scale

    def light_image(self, path: str) -> torch.Tensor:
        """(H, W, 3) image of one light alone (for AOVs and tests)."""
        state = self._lights[path]
        scale = torch.as_tensor(colour_scale(state.light), device=self.gbuffer.device,
                                dtype=self.gbuffer.position.dtype)
        image = self.gbuffer.scatter(scale * self._unit_image(state))
        s = self.supersampling
        if s > 1:
            height, width, _ = image.shape
            image = image.reshape(height // s, s, width // s, s, 3).mean(dim=(1, 3))
        return image * self.exposure_scale

    # -- per-light stages -----------------------------------------------------------------------

    def _chunks(self) -> list[slice]:
        n, step = self.gbuffer.num_samples, self.settings.chunk_points
        return [slice(i, min(i + step, n)) for i in range(0, n, step)]

    def _num_samples(self, light: Light) -> int:
        if is_delta_light(light):
            return 1
        return self.settings.dome_samples if light.kind is LightKind.DOME else self.settings.area_samples

    def _fixed_u(self, num_samples: int) -> torch.Tensor:
        if num_samples not in self._u:
            g = self.gbuffer
            self._u[num_samples] = fixed_light_samples(g.num_samples, num_samples, self.settings.seed,
                                                       g.device, g.position.dtype)
        return self._u[num_samples]

    def _sample_and_test(self, state: _LightState) -> None:
        """Light samples and their shadow factors, for the unit light (colour is a rescale)."""
        g = self.gbuffer
        unit = unit_light(state.light)
        u = self._fixed_u(self._num_samples(unit))
        state.samples, state.shadow = [], []
        for chunk in self._chunks():
            sample = sample_light(unit, g.position[chunk], u[chunk])
            distance = self.visibility.occluder_distance(unit, g.position[chunk], g.geometric_normal[chunk],
                                                         sample.direction, sample.distance)
            state.samples.append(sample)
            state.shadow.append(shadow_factor(unit.shadow, torch.isfinite(distance), distance))
        self.counters["visibility"] += 1

    def _unit_image(self, state: _LightState) -> torch.Tensor:
        if state.unit_image is not None:
            return state.unit_image
        if not state.samples:
            self._sample_and_test(state)
        g = self.gbuffer
        light = unit_light(state.light)
        out = torch.zeros_like(g.position)
        for chunk, sample, shadow in zip(self._chunks(), state.samples, state.shadow):
            wi_local = to_local(sample.direction, g.tangent[chunk, None], g.bitangent[chunk, None],
                                g.normal[chunk, None])
            facing = (sample.direction * g.geometric_normal[chunk, None]).sum(-1) > 0
            weight = sample.weight() * shadow * facing.unsqueeze(-1)
            reflected = reflected_radiance(g.params.index(chunk).with_sample_axis(), self._wo_local[chunk, None],
                                           wi_local, weight, light.diffuse, light.specular)
            out[chunk] = reflected.mean(dim=1)
        state.unit_image = out
        self.counters["shading"] += 1
        return out


def open_relighter(path: str | os.PathLike, device: str | torch.device = "cpu", shadows: str = "embree",
                   lights_layer: str | os.PathLike | None = None,
                   settings: RelightSettings = RelightSettings()) -> Relighter:
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
    occluders = np.ascontiguousarray(load_npy(layer_path, description, "occluders"))
    if shadows == "embree":
        visibility = RayVisibility(EmbreeCaster(occluders))
    elif shadows == "shadowmaps":
        from relight_torch.visibility.shadow_maps import ShadowMapVisibility  # noqa: PLC0415 (being written)
        visibility = ShadowMapVisibility(torch.from_numpy(occluders).to(device))
    else:
        raise RelightError(f"shadows must be 'embree' or 'shadowmaps', got {shadows!r}")
    relighter = Relighter(gbuffer, visibility, description.supersampling, description.exposure_scale, settings)
    relighter.description = description
    relighter.set_lights(shot_lights(description, lights_layer))
    return relighter


def shot_lights(description: CacheDescription, lights_layer: str | os.PathLike | None = None) -> list[Light]:
    """The lights of the cache's shot, at the baked time, with `lights_layer` composed over them."""
    stage = open_stage(description.source, lights_layer)
    return read_stage_lights(stage, time_code(stage, description.parameters.get("time")))
