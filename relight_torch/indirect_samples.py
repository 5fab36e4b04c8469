"""Gather samples: the diffuse points that carry light from the lights to the view samples.

They are spread over every surface, visible or not, and stored in the order of the square
n x n texture their Haar transform works on (row-major: sample t sits at row t // n, column
t % n), so that a light vector over gathers reshapes to an (n, n, C) image.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import torch

from relight_torch.diffuse_light import diffuse_radiance
from relight_torch.lights.light import Light
from relight_torch.visibility import Visibility


@dataclass(frozen=True)
class GatherSamples:
    """G = n^2 gather samples in texture order.

    Attributes:
        position: (G, 3) world position.
        normal: (G, 3) unit normal of the side that receives and emits (the triangle's winding).
        albedo: (G, 3) albedo of the diffuse re-emission (the bake's: the BRDF's bihemispherical
            reflectance, `pipeline.bake.gather_cloud.reemitted_albedo`).
        emission: (G, 3) emitted radiance (emissiveColor).
        area: (G,) world surface area each sample stands for.
        object_id: (G,) int64 index of each sample's object into the cache's object paths (for
            light links), or None when unknown (a cache baked before gathers carried it).
    """

    position: torch.Tensor
    normal: torch.Tensor
    albedo: torch.Tensor
    emission: torch.Tensor
    area: torch.Tensor
    object_id: torch.Tensor | None = None

    def __post_init__(self) -> None:
        num = self.position.shape[0]
        side = math.isqrt(num)
        if side * side != num or side & (side - 1):
            raise ValueError(f"the number of gathers must be a power of 4, got {num}")
        for name in ("position", "normal", "albedo", "emission"):
            if getattr(self, name).shape != (num, 3):
                raise ValueError(f"GatherSamples.{name} must be ({num}, 3), got {tuple(getattr(self, name).shape)}")
        if self.area.shape != (num,):
            raise ValueError(f"GatherSamples.area must be ({num},), got {tuple(self.area.shape)}")
        if self.object_id is not None and self.object_id.shape != (num,):
            raise ValueError(f"GatherSamples.object_id must be ({num},), got {tuple(self.object_id.shape)}")

    @property
    def num_gathers(self) -> int:
        return int(self.position.shape[0])

    @property
    def side(self) -> int:
        """n, the side of the square texture."""
        return math.isqrt(self.num_gathers)

    def to(self, device: torch.device | str, dtype: torch.dtype = torch.float32) -> GatherSamples:
        """Floating fields cast to `dtype`; the object ids stay int64."""
        moved = {f.name: getattr(self, f.name).to(device, dtype) for f in fields(self) if f.name != "object_id"}
        return GatherSamples(**moved, object_id=None if self.object_id is None else self.object_id.to(device))


def gather_payload_name(field: str) -> str:
    """The cache payload of a `GatherSamples` field: 'object_id' -> 'gatherObjectId'."""
    return "gather" + "".join(word.capitalize() for word in field.split("_"))


def gather_radiance(
    light: Light,
    gathers: GatherSamples,
    visibility: Visibility,
    num_samples: int,
    seed: int = 0,
    chunk_points: int = 1 << 16,
    object_paths: Sequence[str] | None = None,
) -> torch.Tensor:
    """Radiance (G, 3) leaving each gather after one diffuse reflection of `light`.

    L = diffuse * albedo / pi * E, with E the irradiance from `num_samples` fixed light samples per
    gather (the view samples' light kernels and visibility: `sample_light`, `occluder_distance`,
    `shadow_factor`), on the side the gather's normal points to. The light's light link masks
    the gathers of other objects and its shadow link picks the occluders (`diffuse_radiance`).

    Args:
        light: the light (its colour included; pass a unit light to cache per light).
        gathers: the gather samples (device and dtype of the result).
        visibility: shadow queries, as for the view samples.
        num_samples: light samples per gather (1 for delta lights).
        seed: seed of the fixed sample pattern.
        chunk_points: gathers processed together.
        object_paths: the cache's object prim paths (`gathers.object_id` indexes them); needed
            only for a light with a light link.
    """
    return diffuse_radiance(
        light,
        gathers.position,
        gathers.normal,
        gathers.albedo,
        visibility,
        num_samples,
        seed,
        chunk_points,
        gathers.object_id,
        object_paths,
    )
