"""The transfer relighter: direct light from the direct `Relighter`, plus indirect light.

Per light, linear as the direct part: the unit light's gather radiance g_d (one reflection off
the gathers, `gather_radiance`) and its indirect image F (I + M + ... + M^(B-1)) g_d are cached,
and scaled by the light's colour factor at render time. A colour edit therefore re-renders
nothing; a move or a reshape recomputes that light's gather light and one pass of sparse
products; other lights keep theirs. Emissive gathers add a light-independent term, computed once.
"""

from __future__ import annotations

import collections
import dataclasses

import numpy as np
import torch

from relight_torch.lights.emission import is_delta_light
from relight_torch.indirect import IndirectRelighter
from relight_torch.lights.light import Light, LightKind
from relight_torch.relighter import Relighter, colour_scale, light_group, unit_light
from relight_torch.transfer.gathers import GatherSamples, gather_radiance
from relight_torch.transfer.haar import haar2d
from relight_torch.transfer.sparse import SparseRows


def _frozen(value) -> object:
    """A hashable, comparable snapshot of a light field (arrays by content, dataclasses by field)."""
    if isinstance(value, np.ndarray):
        return value.shape, value.dtype.str, value.tobytes()
    if dataclasses.is_dataclass(value):
        return tuple((f.name, _frozen(getattr(value, f.name))) for f in dataclasses.fields(value))
    return value


@dataclasses.dataclass
class _IndirectState:
    key: object                 # `_frozen(unit_light(light))`: what the cached work depends on
    unit_indirect: torch.Tensor  # (R, 3) indirect radiance of the unit light at the F rows


class TransferRelighter(IndirectRelighter):
    """Direct + indirect relighting of one transfer cache.

    Args:
        direct: the direct relighter of the cache's deep framebuffer (lights live there; its
            visibility also answers the gathers' shadow queries).
        gathers: the G gather samples, texture order, on the direct relighter's device.
        view_pixels: (R,) int64 pixel (row * W + col) of each F row.
        final_gather: F, R wavelet rows over G.
        bounce: M, G wavelet rows over G, or None for one bounce.
        num_bounces: B >= 1; M is applied B - 1 times.
        gather_samples: light samples per gather for area lights; None: the direct settings'
            `area_samples` (dome lights always take `dome_samples`). The gather light costs about
            as many shadow rays as samples. Fewer are safe for lights far from every surface (64 x 64
            Cornell box, 16,384 gathers: 1 / 4 / 16 samples put the indirect image 2.5 / 0.7 / 0.4 %
            RMS from 64 samples) but not near one: with a lamp 10 mm from a wall the indirect mean
            fell from 0.95 to 0.70 of the reference at 4 samples, so the default keeps the direct count.
    """

    def __init__(self, direct: Relighter, gathers: GatherSamples, view_pixels: torch.Tensor,
                 final_gather: SparseRows, bounce: SparseRows | None = None, num_bounces: int = 1,
                 gather_samples: int | None = None):
        if final_gather.num_columns != gathers.num_gathers or final_gather.num_rows != view_pixels.shape[0]:
            raise ValueError(f"F is {final_gather.num_rows}x{final_gather.num_columns}; expected "
                             f"{view_pixels.shape[0]} view rows x {gathers.num_gathers} gathers")
        if num_bounces < 1 or (num_bounces > 1 and (bounce is None or bounce.num_rows != gathers.num_gathers)):
            raise ValueError(f"{num_bounces} bounces need M as {gathers.num_gathers} rows (got "
                             f"{None if bounce is None else bounce.num_rows})")
        if gather_samples is not None and gather_samples < 1:
            raise ValueError(f"gather_samples must be >= 1, got {gather_samples}")
        super().__init__(direct)
        self.gathers = gathers
        self.view_pixels = view_pixels
        self.final_gather = final_gather
        self.bounce = bounce
        self.num_bounces = num_bounces
        self.gather_samples = gather_samples
        self.counters: collections.Counter[str] = collections.Counter()
        self._emission_indirect: torch.Tensor | None = None

    # -- rendering ------------------------------------------------------------------------------

    def indirect_image(self) -> torch.Tensor:
        """(H, W, 3) indirect light alone, camera exposure applied."""
        return self._rows_to_image(self.indirect_rows())

    def light_group_images(self) -> dict[str, torch.Tensor]:
        """'<group>_direct' and '<group>_indirect' -> (H, W, 3) images of each light group's lights
        (`relighter.light_group`); with `emission_image()` they sum to `render()` (within rounding)."""
        emission = self._emission_rows()
        indirect: dict[str, torch.Tensor] = {}
        for light in self.lights:
            rows = indirect.setdefault(light_group(light), torch.zeros_like(emission))
            scale = torch.as_tensor(colour_scale(light), device=rows.device, dtype=rows.dtype)
            if bool((scale != 0).any()):
                rows.add_(scale * self._unit_indirect(light))
        images = {}
        for group, direct in self.direct.light_group_images().items():
            images[f"{group}_direct"] = direct
            images[f"{group}_indirect"] = self._rows_to_image(indirect[group])
        return images

    def emission_image(self) -> torch.Tensor:
        """(H, W, 3) the surfaces' own emission, seen directly and through the gathers."""
        return self.direct.emission_image() + self._rows_to_image(self._emission_rows())

    def _rows_to_image(self, rows: torch.Tensor) -> torch.Tensor:
        """(R, 3) values at the F rows' view samples -> (H, W, 3) image, camera exposure applied."""
        height, width = (size // self.direct.supersampling for size in self.direct.gbuffer.image_size)
        image = rows.new_zeros((height * width, 3))
        image[self.view_pixels] = rows
        return image.reshape(height, width, 3) * self.direct.exposure_scale

    def indirect_rows(self) -> torch.Tensor:
        """(R, 3) indirect radiance at the F rows' view samples (exposure not applied)."""
        total = self._emission_rows()
        for light in self.lights:
            scale = torch.as_tensor(colour_scale(light), device=total.device, dtype=total.dtype)
            if bool((scale == 0).all()):
                continue
            total = total + scale * self._unit_indirect(light)
        return total

    def transfer(self, radiance: torch.Tensor) -> torch.Tensor:
        """F (I + M + ... + M^(B-1)) radiance: (G, 3) gather radiance -> (R, 3) at the view rows."""
        total, bounced = radiance, radiance
        for _ in range(self.num_bounces - 1):
            bounced = self.bounce.matmul(self._wavelet(bounced))
            total = total + bounced
        self.counters["transfer"] += 1
        return self.final_gather.matmul(self._wavelet(total))

    def _wavelet(self, radiance: torch.Tensor) -> torch.Tensor:
        """(G, 3) gather values in texture order -> (G, 3) Haar coefficients, flattened row-major."""
        side = self.gathers.side
        return haar2d(radiance.reshape(side, side, 3)).reshape(-1, 3)

    # -- cached stages --------------------------------------------------------------------------

    def _emission_rows(self) -> torch.Tensor:
        if self._emission_indirect is None:
            self._emission_indirect = self.transfer(self.gathers.emission)
        return self._emission_indirect

    def _unit_indirect(self, light: Light) -> torch.Tensor:
        unit = unit_light(light)
        key = _frozen(unit)
        state = self._per_light.get(light.path)
        if state is None or state.key != key:
            settings = self.direct.settings
            num_samples = 1 if is_delta_light(unit) else (
                settings.dome_samples if unit.kind is LightKind.DOME else self.gather_samples or settings.area_samples)
            radiance = gather_radiance(unit, self.gathers, self.direct.visibility, num_samples, settings.seed)
            self.counters["gather_light"] += 1
            state = _IndirectState(key, self.transfer(radiance))
            self._per_light[light.path] = state
        return state.unit_indirect
