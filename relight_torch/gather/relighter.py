"""Relighting a 'gather' cache: direct light plus one clustered-gather bounce (the clustered-gather paper, eq. 3).

    I(pixel i) = sum_k c_ik I(v_k),   I(v_k) = sum_j D(g_kj) w_kj

v_k are the view representatives, g_kj their clustered gather points, w_kj the gather weights
baked with them and c_ik the radial-basis weights of pixel i's nearest representatives. Two
representative sets are kept: 'diffuse' stores weights without the receiver's diffuse albedo
(it interpolates irradiance, and each pixel multiplies by its own albedo, so textures stay
sharp) and 'glossy' stores the specular lobes' weights (it interpolates radiance).

The clustered gathers of both sets index U shared surface points (`pipeline.bake.gather.
surface_points`: gathers of neighbouring representatives land on the same surfaces), so D is
computed once per point. Per light, linear as the direct part: D on every shared point in one
batched pass for the unit light (`diffuse_radiance`, light links and shadow links applied per
point object), reduced per representative by weighted embedding bags and reconstructed per pixel;
the (P, 3) result is cached and scaled by the light's colour factor, so a colour edit recomputes
nothing. The shadow answers are remembered per light geometry (`RememberedVisibility`), so a
shaping edit re-weights the same samples without tracing; only a move or resize traces again.
"""

from __future__ import annotations

import collections
import dataclasses
import functools

import torch

from relight_torch.diffuse_light import diffuse_radiance
from relight_torch.direct.images import unit_light
from relight_torch.direct.relighter import Relighter
from relight_torch.gather.reconstruction import interpolate
from relight_torch.gather.remembered import RememberedVisibility
from relight_torch.indirect import IndirectRelighter, gather_light_key
from relight_torch.lights.light import Light
from relight_torch.protocol import tensor_bytes

SET_NAMES = ("diffuse", "glossy")
GREY_TOLERANCE = 1e-5
"""Relative spread of a gather weight's three channels below which it is read as grey. The diffuse
set's weights (the diffuse lobe over the receiver's albedo) are grey up to float rounding: 7e-7 on
the Cornell box at 400 x 400, where reading them as grey makes a shaping edit's gathers 2x faster."""
DEFAULT_GATHER_SAMPLES = 1
"""Light samples per shared surface point for area lights (see `GatherRelighter`). Measured on the
Cornell box at 24 x 24 (`pipeline.benchmarks.gather_sweep`): 1, 4 and 16 samples within 0.1 dB of
each other, full and indirect, so 1 keeps the light move cheapest."""


@dataclasses.dataclass(frozen=True)
class SurfacePoints:
    """The U surface points the clustered gathers of every set share (lit once per light edit).

    Attributes:
        position: (U, 3) world positions.
        normal: (U, 3) unit receiving normals.
        albedo: (U, 3) diffuse albedo.
        object_id: (U,) int64 object of each point (index into the cache's object paths).
    """

    position: torch.Tensor
    normal: torch.Tensor
    albedo: torch.Tensor
    object_id: torch.Tensor

    def __post_init__(self) -> None:
        num_points = self.position.shape[0]
        for name in ("position", "normal", "albedo"):
            if getattr(self, name).shape != (num_points, 3):
                raise ValueError(
                    f"SurfacePoints.{name} must be ({num_points}, 3), got {tuple(getattr(self, name).shape)}"
                )
        if self.object_id.shape != (num_points,):
            raise ValueError(f"SurfacePoints.object_id must be ({num_points},), got {tuple(self.object_id.shape)}")

    @property
    def num_points(self) -> int:
        return int(self.position.shape[0])

    @property
    def num_bytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in dataclasses.astuple(self))

    def to(self, device: torch.device | str, dtype: torch.dtype = torch.float32) -> SurfacePoints:
        position, normal, albedo = (t.to(device, dtype) for t in (self.position, self.normal, self.albedo))
        return SurfacePoints(position, normal, albedo, object_id=self.object_id.to(device, torch.int64))


@dataclasses.dataclass(frozen=True)
class GatherSet:
    """One set of view representatives with their clustered gathers (CSR by representative).

    Attributes:
        index: (G,) int64 shared surface point of each clustered gather (CSR columns).
        weight: (G, 3) its gather weight w = rho cos / (pdf N), summed over the gathers merged into
            it (unitless; CSR values).
        offsets: (R + 1,) int64: representative k owns entries offsets[k]:offsets[k + 1].
        neighbours: (P, k) int64 representatives of each view pixel.
        rbf: (P, k) their radial-basis weights (rows sum to 1, or 0 for pixels outside the set).
    """

    index: torch.Tensor
    weight: torch.Tensor
    offsets: torch.Tensor
    neighbours: torch.Tensor
    rbf: torch.Tensor

    def __post_init__(self) -> None:
        num_gathers = self.index.shape[0]
        if self.index.ndim != 1 or self.weight.shape != (num_gathers, 3):
            raise ValueError(
                f"GatherSet.index must be (G,) and .weight (G, 3), got {tuple(self.index.shape)} "
                f"and {tuple(self.weight.shape)}"
            )
        if num_gathers and int(self.index.min()) < 0:
            raise ValueError("GatherSet.index must not be negative")
        if (
            self.offsets.ndim != 1
            or int(self.offsets[0]) != 0
            or int(self.offsets[-1]) != num_gathers
            or bool((self.offsets[1:] < self.offsets[:-1]).any())
        ):
            raise ValueError(f"GatherSet.offsets must rise from 0 to {num_gathers}")
        if self.neighbours.shape != self.rbf.shape or self.neighbours.ndim != 2:
            raise ValueError("GatherSet.neighbours and .rbf must both be (P, k)")
        if self.neighbours.numel() and (
            int(self.neighbours.min()) < 0 or int(self.neighbours.max()) >= self.num_representatives
        ):
            raise ValueError(f"GatherSet.neighbours must index {self.num_representatives} representatives")

    @property
    def num_representatives(self) -> int:
        return int(self.offsets.shape[0]) - 1

    @property
    def num_gathers(self) -> int:
        return int(self.index.shape[0])

    @property
    def num_bytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in dataclasses.astuple(self))

    def to(self, device: torch.device | str, dtype: torch.dtype = torch.float32) -> GatherSet:
        moved = {f.name: getattr(self, f.name).to(device) for f in dataclasses.fields(self)}
        for name in ("weight", "rbf"):
            moved[name] = moved[name].to(dtype)
        for name in ("index", "offsets", "neighbours"):
            moved[name] = moved[name].long()
        return GatherSet(**moved)

    def representative_values(self, radiance: torch.Tensor) -> torch.Tensor:
        """(R, 3) sum_j D(g_kj) w_kj from (U, 3) radiance D leaving the shared surface points."""
        # Weighted embedding bags: ~5x faster on CPU than indexing (G, 3) rows and adding them per
        # representative (index_add_), and faster than a CSR sparse product. Grey weights (the
        # diffuse set's, and the glossy set's of white-specular or specular-free materials) take
        # one bag over all three colours, else one bag per colour (~3x the time).
        if self._grey:
            return torch.nn.functional.embedding_bag(
                self.index,
                radiance,
                self.offsets,
                mode="sum",
                per_sample_weights=self._grey_weight.to(radiance.dtype),
                include_last_offset=True,
            )
        return torch.stack(
            [
                torch.nn.functional.embedding_bag(
                    self.index,
                    radiance[:, c : c + 1].contiguous(),
                    self.offsets,
                    mode="sum",
                    per_sample_weights=weight.to(radiance.dtype),
                    include_last_offset=True,
                )[:, 0]
                for c, weight in enumerate(self._channel_weights)
            ],
            dim=-1,
        )

    @functools.cached_property
    def _grey(self) -> bool:
        """Whether every weight's three channels are equal within `GREY_TOLERANCE`."""
        spread = self.weight.amax(-1) - self.weight.amin(-1)
        return bool((spread <= GREY_TOLERANCE * self.weight.abs().amax(-1)).all())

    @functools.cached_property
    def _grey_weight(self) -> torch.Tensor:
        """(G,) the mean of each weight's channels (the weight, when `_grey`)."""
        return self.weight.mean(-1)

    @functools.cached_property
    def _channel_weights(self) -> torch.Tensor:
        """(3, G) the weights channel-major: the per-colour bags read contiguous rows."""
        return self.weight.t().contiguous()


class GatherRelighter(IndirectRelighter[tuple[object, torch.Tensor]]):
    """Direct + clustered-gather indirect relighting of one 'gather' cache.

    Args:
        direct: the direct relighter of the cache's deep framebuffer (it holds the lights; its
            visibility, remembered per light (`RememberedVisibility`), answers the gathers'
            shadow queries).
        points: the surface points the sets' gathers share, on the direct relighter's device and dtype.
        sets: {'diffuse': GatherSet, 'glossy': GatherSet} (either may be absent), likewise.
        view_pixels: (P,) int64 pixel (row * W + col) of each view sample.
        view_albedo: (P, 3) diffuse albedo of each view sample (multiplies the diffuse set).
        gather_samples: light samples per surface point for area lights and domes (delta lights
            take one). Each representative sums ~100 points, whose fixed samples are rotated
            differently, so one sample per point suffices (`DEFAULT_GATHER_SAMPLES`).

    Attributes:
        counters: 'gather_light' passes run so far (one per light edit that is more than a colour edit).
        visibility: the remembered visibility of the gathers (its counters say how many queries traced).
    """

    def __init__(
        self,
        direct: Relighter,
        points: SurfacePoints,
        sets: dict[str, GatherSet],
        view_pixels: torch.Tensor,
        view_albedo: torch.Tensor,
        gather_samples: int = DEFAULT_GATHER_SAMPLES,
    ):
        unknown = set(sets) - set(SET_NAMES)
        if unknown or not sets:
            raise ValueError(f"gather sets must be among {SET_NAMES}, got {sorted(sets)}")
        if gather_samples < 1:
            raise ValueError(f"gather_samples must be >= 1, got {gather_samples}")
        for name, gather_set in sets.items():
            if gather_set.neighbours.shape[0] != view_pixels.shape[0]:
                raise ValueError(
                    f"the {name} set reconstructs {gather_set.neighbours.shape[0]} pixels, "
                    f"expected {view_pixels.shape[0]}"
                )
            if gather_set.num_gathers and int(gather_set.index.max()) >= points.num_points:
                raise ValueError(f"the {name} set indexes past the {points.num_points} surface points")
        if view_albedo.shape != (view_pixels.shape[0], 3):
            raise ValueError(f"view_albedo must be ({view_pixels.shape[0]}, 3), got {tuple(view_albedo.shape)}")
        super().__init__(direct)
        self.points = points
        self.sets = sets
        self.view_pixels = view_pixels
        self.view_albedo = view_albedo
        self.gather_samples = gather_samples
        self.visibility = RememberedVisibility(direct.visibility)
        self.counters: collections.Counter[str] = collections.Counter()

    @property
    def cache_bytes(self) -> int:
        """Bytes of the baked points and sets held in memory."""
        return self.points.num_bytes + sum(s.num_bytes for s in self.sets.values())

    def remove_light(self, path: str) -> None:
        super().remove_light(path)
        self.visibility.forget(path)

    def set_lights(self, lights: list[Light]) -> None:
        """Replace the whole rig; unchanged lights keep their cached work."""
        for path in {light.path for light in self.lights} - {light.path for light in lights}:
            self.visibility.forget(path)
        super().set_lights(lights)

    # -- rendering ------------------------------------------------------------------------------

    def reconstruct(self, radiance: torch.Tensor) -> torch.Tensor:
        """Equation 3: (U, 3) radiance leaving the shared surface points -> (P, 3) per pixel."""
        total = torch.zeros_like(self.view_albedo)
        for name, gather_set in self.sets.items():
            pixels = interpolate(gather_set.representative_values(radiance), gather_set.neighbours, gather_set.rbf)
            if name == "diffuse":
                total.addcmul_(pixels, self.view_albedo)
            else:
                total.add_(pixels)
        return total

    def surface_radiance(self, light: Light) -> torch.Tensor:
        """(U, 3) radiance D leaving the shared surface points, lit by `light` (its colour included)."""
        p = self.points
        return diffuse_radiance(
            light,
            p.position,
            p.normal,
            p.albedo,
            self.visibility,
            self._gather_samples(light, self.gather_samples),
            self.direct.settings.seed,
            object_id=p.object_id,
            object_paths=self.direct.object_paths,
        )

    def _indirect_bytes(self) -> int:
        return tensor_bytes(*(image for _, image in self._per_light.values()))

    def _unit_indirect(self, light: Light) -> torch.Tensor:
        unit = unit_light(light)
        key = gather_light_key(unit)
        cached = self._per_light.get(light.path)
        if cached is None or cached[0] != key:
            self.counters["gather_light"] += 1
            cached = (key, self.reconstruct(self.surface_radiance(unit)))
            self._per_light[light.path] = cached
        return cached[1]
