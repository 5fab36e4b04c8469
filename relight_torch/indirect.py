"""What the indirect relighters share: the direct Relighter holds the lights; each method adds an
indirect image and keeps per-light work keyed by light path, dropped when a light goes away.

Indirect light is linear in the lights like direct light: a method supplies, per light, the
indirect radiance of the unit light (`unit_light`: intensity 1, white) at its R view samples, and
the base scales and sums them, per light for the image and per light group for the AOVs.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Generic, TypeVar

import torch

from relight_torch.direct.images import colour_scale
from relight_torch.direct.relighter import Relighter
from relight_torch.direct.rig import light_group
from relight_torch.lights.emission import is_delta_light
from relight_torch.lights.light import Light, LightKind, light_snapshot
from relight_torch.protocol import Refinement, refuse_material_edit, refuse_progressive

StateT = TypeVar("StateT")
"""A subclass's cached indirect work per light."""


def gather_sample_count(light: Light, area_samples: int, dome_samples: int) -> int:
    """Light samples per gather: 1 for a delta light, `dome_samples` for a dome, else `area_samples`."""
    if is_delta_light(light):
        return 1
    return dome_samples if light.kind is LightKind.DOME else area_samples


def gather_light_key(unit: Light) -> object:
    """What a unit light's diffuse light on gathers depends on: all of it but its AOV group and its
    specular multiplier (gathers reflect diffusely)."""
    return light_snapshot(dataclasses.replace(unit, light_group="", specular=1.0))


class IndirectRelighter(Generic[StateT]):
    """Base of `TransferRelighter` and `GatherRelighter`.

    Subclasses set `self.view_pixels` ((R,) int64 pixel row * W + col of each view sample of the
    indirect image) and `self._per_light` (light path -> cached indirect work, the `StateT` a
    subclass names: `IndirectRelighter[_IndirectState]`), and implement
    `_unit_indirect(light)`; they may override `_emission_rows()` (light-independent indirect
    light, zero by default).

    Args:
        direct: the direct relighter of the same cache; it owns the light rig.
    """

    view_pixels: torch.Tensor
    material_edits = False  # the transport was baked with the materials (`CacheRelighter`)
    progressive = False  # a subclass with `_unit_indirect_at` sets it (`CacheRelighter.refine`)
    indirect_scale = 1  # pixels per side of an indirect view sample (`view_pixels` index that image)

    def __init__(self, direct: Relighter):
        self.direct = direct
        self._per_light: dict[str, StateT] = {}
        self._row_of_point: torch.Tensor | None = None  # (N,) see `_rows_of`
        self._static: tuple[object, torch.Tensor] | None = None  # see `_static_indirect`

    @property
    def lights(self) -> list[Light]:
        return self.direct.lights

    @property
    def material_paths(self) -> list[str] | None:
        return self.direct.material_paths

    def set_lights(self, lights: list[Light]) -> None:
        """Replace the whole rig; unchanged lights keep their cached work."""
        self.direct.set_lights(lights)
        for path in set(self._per_light) - {light.path for light in lights}:
            del self._per_light[path]

    def set_light(self, light: Light) -> None:
        """Add or edit a light (matched by path)."""
        self.direct.set_light(light)

    def remove_light(self, path: str) -> None:
        self.direct.remove_light(path)
        self._per_light.pop(path, None)

    def set_material_edits(self, edits: Mapping[int | str, Mapping[str, object]]) -> None:
        refuse_material_edit(self)

    def edit_material(self, material: int | str, **values: object) -> None:
        refuse_material_edit(self)

    def held_bytes(self) -> int:
        """`CacheRelighter.held_bytes`: the direct relighter's and the per-light indirect light (`_indirect_bytes`)."""
        return self.direct.held_bytes() + self._indirect_bytes()

    def _indirect_bytes(self) -> int:
        """Bytes of the per-light indirect work kept between renders (`_per_light`)."""
        raise NotImplementedError

    def render(self) -> torch.Tensor:
        """(H, W, 3) linear image: direct (supersampled) + indirect (per pixel), exposure applied."""
        return self.direct.render() + self.indirect_image()

    # -- progressive refinement (`CacheRelighter.refine`) ---------------------------------------

    @property
    def edits(self) -> int:
        return self.direct.edits

    def pending(self, stride: int | None) -> float:
        """`CacheRelighter.pending`: the direct relighter's (indirect rows cost far less per row)."""
        if not self.progressive:
            refuse_progressive(self)
        return self.direct.pending(stride)

    def refine(self, stride: int | None) -> Refinement:
        """`CacheRelighter.refine`: the direct relighter's coarse values of the changed lights plus
        their unit indirect light at the view samples of the level's points (the rows made kept:
        `_unit_indirect_at`), upsampled together over the exact image (direct and indirect) of
        the others. `stride` None: `render()`, the rows made by coarse frames not multiplied again."""
        if not self.progressive:
            refuse_progressive(self)
        changed = self.direct.changed_lights()
        if stride is None or not changed:
            evaluated, work = self.direct.complete()
            return Refinement(self.render(), evaluated, work, True)
        static = self._static_indirect(changed)
        level, values, evaluated, work = self.direct.coarse_values(stride)
        rows = self._rows_of(level.points)
        seen = rows >= 0
        rows = rows[seen]
        for light in changed:
            scale = self._scale(light, values)
            if bool((scale != 0).any()):
                values[seen, :3] += self._unit_indirect_at(light, rows) * scale
        return Refinement(self.direct.coarse_image(level, values) + static, evaluated, work, False)

    def _unit_indirect_at(self, light: Light, rows: torch.Tensor) -> torch.Tensor:
        """(K, 3) `_unit_indirect(light)` at view samples `rows` (K,), its work kept for the rest."""
        raise NotImplementedError

    def _rows_of(self, points: torch.Tensor) -> torch.Tensor:
        """(M,) the view sample (row of `view_pixels`) whose pixel holds each of the direct
        relighter's shading points `points` (M,), -1 where none does."""
        if self._row_of_point is None:
            g, s = self.direct.gbuffer, self.direct.supersampling
            sub_width = g.image_size[1]
            width = sub_width // s // self.indirect_scale
            row, col = torch.div(g.pixel_index, sub_width, rounding_mode="floor"), g.pixel_index % sub_width
            pixel = torch.div(row, s * self.indirect_scale, rounding_mode="floor") * width + torch.div(
                col, s * self.indirect_scale, rounding_mode="floor"
            )
            height = g.image_size[0] // s // self.indirect_scale
            row_of_pixel = torch.full((height * width,), -1, dtype=torch.int64, device=g.device)
            row_of_pixel[self.view_pixels] = torch.arange(self.view_pixels.shape[0], device=g.device)
            self._row_of_point = row_of_pixel[pixel.clamp(max=height * width - 1)]
        return self._row_of_point.index_select(0, points)

    def _static_indirect(self, changed: list[Light]) -> torch.Tensor:
        """(H, W, 3) the indirect image of the emission and the lights not in `changed` (exposure
        applied), kept while those stay the same (`Relighter.unchanged_key`)."""
        key = self.direct.unchanged_key()
        if self._static is None or self._static[0] != key:
            paths = {light.path for light in changed}
            total = self._emission_rows()
            for light in self.lights:
                scale = self._scale(light, total)
                if light.path not in paths and bool((scale != 0).any()):
                    total = total + scale * self._unit_indirect(light)
            self._static = (key, self._rows_to_image(total))
        return self._static[1]

    def indirect_image(self) -> torch.Tensor:
        """(H, W, 3) indirect light alone, camera exposure applied."""
        return self._rows_to_image(self.indirect_rows())

    def indirect_rows(self) -> torch.Tensor:
        """(R, 3) indirect radiance at the view samples (exposure not applied)."""
        total = self._emission_rows()
        for light in self.lights:
            scale = self._scale(light, total)
            if bool((scale != 0).any()):
                total = total + scale * self._unit_indirect(light)
        return total

    def light_group_images(self) -> dict[str, torch.Tensor]:
        """'<group>_direct' and '<group>_indirect' -> (H, W, 3) images of each light group's lights
        (`direct.rig.light_group`), exposure applied; with `emission_image()` they sum to `render()`
        within float rounding."""
        emission = self._emission_rows()
        indirect: dict[str, torch.Tensor] = {}
        for light in self.lights:
            rows = indirect.setdefault(light_group(light), torch.zeros_like(emission))
            scale = self._scale(light, rows)
            if bool((scale != 0).any()):
                rows.add_(scale * self._unit_indirect(light))
        images = {}
        for group, direct in self.direct.light_group_images().items():
            images[f"{group}_direct"] = direct
            images[f"{group}_indirect"] = self._rows_to_image(indirect[group])
        return images

    def emission_image(self) -> torch.Tensor:
        """(H, W, 3) the surfaces' own emission, seen directly and through the indirect transport."""
        return self.direct.emission_image() + self._rows_to_image(self._emission_rows())

    def _unit_indirect(self, light: Light) -> torch.Tensor:
        """(R, 3) indirect radiance of `unit_light(light)` at the view samples (cached per light)."""
        raise NotImplementedError

    def _emission_rows(self) -> torch.Tensor:
        """(R, 3) indirect light of the surfaces' own emission; zero unless a method carries it."""
        return torch.zeros(
            (self.view_pixels.shape[0], 3), device=self.view_pixels.device, dtype=self.direct.gbuffer.position.dtype
        )

    def _gather_samples(self, light: Light, area_samples: int) -> int:
        """Light samples per gather (`gather_sample_count`, the direct settings' dome count)."""
        return gather_sample_count(light, area_samples, self.direct.settings.dome_samples)

    @staticmethod
    def _scale(light: Light, like: torch.Tensor) -> torch.Tensor:
        """(3,) the light's colour factor (`colour_scale`) as a tensor like `like`."""
        return torch.as_tensor(colour_scale(light), device=like.device, dtype=like.dtype)

    def _rows_to_image(self, rows: torch.Tensor) -> torch.Tensor:
        """(R, 3) values at the view samples -> (H, W, 3) image, camera exposure applied."""
        height, width = (size // self.direct.supersampling for size in self.direct.gbuffer.image_size)
        image = rows.new_zeros((height * width, 3))
        image[self.view_pixels] = rows
        return image.reshape(height, width, 3) * self.direct.exposure_scale
