"""Relighting a 'gather' cache: direct light plus one clustered-gather bounce (seed paper, eq. 3).

    I(pixel i) = sum_k c_ik I(v_k),   I(v_k) = sum_j D(g_kj) w_kj

v_k are the view representatives, g_kj their clustered gather points, w_kj the gather weights
baked with them and c_ik the radial-basis weights of pixel i's nearest representatives. Two
representative sets are kept: 'diffuse' stores weights without the receiver's diffuse albedo
(it interpolates irradiance, and each pixel multiplies by its own albedo, so textures stay
sharp) and 'glossy' stores the specular lobes' weights (it interpolates radiance).

Per light, linear as the direct part: D on every clustered gather point of both sets is computed
in one batched pass for the unit light, reduced per representative and reconstructed per pixel;
the (P, 3) result is cached and scaled by the light's colour factor, so a colour edit recomputes
nothing and a move or reshape recomputes that light's gathers only.
"""

from __future__ import annotations

import collections
import dataclasses

import numpy as np
import torch

from relight_torch.diffuse_light import diffuse_radiance
from relight_torch.gather.reconstruction import interpolate
from relight_torch.lights.emission import is_delta_light
from relight_torch.indirect import IndirectRelighter
from relight_torch.lights.light import Light, LightKind
from relight_torch.relighter import Relighter, colour_scale, unit_light

SET_NAMES = ("diffuse", "glossy")


@dataclasses.dataclass(frozen=True)
class GatherSet:
    """One set of view representatives with their clustered gathers (CSR by representative).

    Attributes:
        position: (G, 3) world position of each clustered gather point.
        normal: (G, 3) unit normal of its receiving side (facing its representative).
        albedo: (G, 3) mean diffuse albedo of its members.
        weight: (G, 3) summed gather weights w = rho cos / (pdf N) of its members (unitless).
        offsets: (R + 1,) int64: representative k owns gathers offsets[k]:offsets[k + 1].
        neighbours: (P, k) int64 representatives of each view pixel.
        rbf: (P, k) their radial-basis weights (rows sum to 1, or 0 for pixels outside the set).
    """

    position: torch.Tensor
    normal: torch.Tensor
    albedo: torch.Tensor
    weight: torch.Tensor
    offsets: torch.Tensor
    neighbours: torch.Tensor
    rbf: torch.Tensor

    def __post_init__(self) -> None:
        num_gathers = self.position.shape[0]
        for name in ("position", "normal", "albedo", "weight"):
            if getattr(self, name).shape != (num_gathers, 3):
                raise ValueError(f"GatherSet.{name} must be ({num_gathers}, 3), got {tuple(getattr(self, name).shape)}")
        if self.offsets.ndim != 1 or int(self.offsets[0]) != 0 or int(self.offsets[-1]) != num_gathers \
                or bool((self.offsets[1:] < self.offsets[:-1]).any()):
            raise ValueError(f"GatherSet.offsets must rise from 0 to {num_gathers}")
        if self.neighbours.shape != self.rbf.shape or self.neighbours.ndim != 2:
            raise ValueError("GatherSet.neighbours and .rbf must both be (P, k)")
        if self.neighbours.numel() and (int(self.neighbours.min()) < 0
                                        or int(self.neighbours.max()) >= self.num_representatives):
            raise ValueError(f"GatherSet.neighbours must index {self.num_representatives} representatives")

    @property
    def num_representatives(self) -> int:
        return int(self.offsets.shape[0]) - 1

    @property
    def num_gathers(self) -> int:
        return int(self.position.shape[0])

    @property
    def num_bytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in dataclasses.astuple(self))

    def to(self, device: torch.device | str, dtype: torch.dtype = torch.float32) -> "GatherSet":
        moved = {f.name: getattr(self, f.name).to(device) for f in dataclasses.fields(self)}
        for name in ("position", "normal", "albedo", "weight", "rbf"):
            moved[name] = moved[name].to(dtype)
        return GatherSet(**moved)

    def representative_values(self, radiance: torch.Tensor) -> torch.Tensor:
        """(R, 3) sum_j D(g_kj) w_kj from (G, 3) radiance D leaving this set's gathers."""
        owner = torch.repeat_interleave(torch.arange(self.num_representatives, device=radiance.device),
                                        self.offsets[1:] - self.offsets[:-1])
        return radiance.new_zeros(self.num_representatives, 3).index_add_(0, owner, radiance * self.weight)


def light_key(light: Light) -> object:
    """A hashable snapshot of every field of a light (arrays by content, nested dataclasses by field)."""
    def frozen(value):
        if isinstance(value, np.ndarray):
            return value.shape, value.dtype.str, value.tobytes()
        if dataclasses.is_dataclass(value):
            return tuple((f.name, frozen(getattr(value, f.name))) for f in dataclasses.fields(value))
        return value
    return frozen(light)


class GatherRelighter(IndirectRelighter):
    """Direct + clustered-gather indirect relighting of one 'gather' cache.

    Args:
        direct: the direct relighter of the cache's deep framebuffer (it holds the lights; its
            visibility answers the gathers' shadow queries).
        sets: {'diffuse': GatherSet, 'glossy': GatherSet} (either may be absent), on the direct
            relighter's device and dtype.
        view_pixels: (P,) int64 pixel (row * W + col) of each view sample.
        view_albedo: (P, 3) diffuse albedo of each view sample (multiplies the diffuse set).

    Attributes:
        counters: 'gather_light' passes run so far (one per light edit that moves its light).
    """

    def __init__(self, direct: Relighter, sets: dict[str, GatherSet], view_pixels: torch.Tensor,
                 view_albedo: torch.Tensor):
        unknown = set(sets) - set(SET_NAMES)
        if unknown or not sets:
            raise ValueError(f"gather sets must be among {SET_NAMES}, got {sorted(sets)}")
        for name, gather_set in sets.items():
            if gather_set.neighbours.shape[0] != view_pixels.shape[0]:
                raise ValueError(f"the {name} set reconstructs {gather_set.neighbours.shape[0]} pixels, "
                                 f"expected {view_pixels.shape[0]}")
        if view_albedo.shape != (view_pixels.shape[0], 3):
            raise ValueError(f"view_albedo must be ({view_pixels.shape[0]}, 3), got {tuple(view_albedo.shape)}")
        super().__init__(direct)
        self.sets = sets
        self.view_pixels = view_pixels
        self.view_albedo = view_albedo
        self.counters: collections.Counter[str] = collections.Counter()
        self._position = torch.cat([s.position for s in sets.values()])
        self._normal = torch.cat([s.normal for s in sets.values()])
        self._albedo = torch.cat([s.albedo for s in sets.values()])

    @property
    def cache_bytes(self) -> int:
        """Bytes of the baked sets held in memory."""
        return sum(s.num_bytes for s in self.sets.values())

    # -- rendering ------------------------------------------------------------------------------

    def indirect_image(self) -> torch.Tensor:
        """(H, W, 3) indirect light alone, camera exposure applied."""
        rows = self.indirect_rows()
        height, width = (size // self.direct.supersampling for size in self.direct.gbuffer.image_size)
        image = rows.new_zeros((height * width, 3))
        image[self.view_pixels] = rows
        return image.reshape(height, width, 3) * self.direct.exposure_scale

    def indirect_rows(self) -> torch.Tensor:
        """(P, 3) indirect radiance at the view samples (exposure not applied)."""
        total = torch.zeros_like(self.view_albedo)
        for light in self.lights:
            scale = torch.as_tensor(colour_scale(light), device=total.device, dtype=total.dtype)
            if bool((scale == 0).all()):
                continue
            total = total + scale * self._unit_indirect(light)
        return total

    def reconstruct(self, radiance: torch.Tensor) -> torch.Tensor:
        """Equation 3: (G, 3) radiance leaving all sets' gathers (concatenated) -> (P, 3) per pixel."""
        total = torch.zeros_like(self.view_albedo)
        for (name, gather_set), part in zip(self.sets.items(),
                                            radiance.split([s.num_gathers for s in self.sets.values()])):
            pixels = interpolate(gather_set.representative_values(part), gather_set.neighbours, gather_set.rbf)
            total = total + (pixels * self.view_albedo if name == "diffuse" else pixels)
        return total

    def _unit_indirect(self, light: Light) -> torch.Tensor:
        unit = unit_light(light)
        key = light_key(unit)
        cached = self._per_light.get(light.path)
        if cached is None or cached[0] != key:
            settings = self.direct.settings
            num_samples = 1 if is_delta_light(unit) else (
                settings.dome_samples if unit.kind is LightKind.DOME else settings.area_samples)
            radiance = diffuse_radiance(unit, self._position, self._normal, self._albedo, self.direct.visibility,
                                        num_samples, settings.seed)
            self.counters["gather_light"] += 1
            cached = (key, self.reconstruct(radiance))
            self._per_light[light.path] = cached
        return cached[1]
