"""A relighter's lights: what an edit of each field invalidates (the geometry and shading keys), the
state kept per light, light groups, and replacing a whole rig light by light."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from relight_torch.direct.transport import Transport
from relight_torch.lights.light import Light, light_snapshot
from relight_torch.protocol import CacheRelighter

if TYPE_CHECKING:
    from relight_torch.direct.progressive import Progress

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


def light_keys(light: Light) -> tuple[tuple[object, ...], tuple[object, ...]]:
    """(geometry key, shading key): what the light's transport depends on (`geometry_key`), and
    that plus its ShapingAPI and Barzel controls, what its unit images depend on."""
    transport_key = geometry_key(light)
    return transport_key, transport_key + _key(light, _SHADING_FIELDS)


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


@dataclass
class LightState:
    """What the relighter keeps of one light, each stage dropped when its key changes (`light_keys`)."""

    light: Light
    geometry_key: tuple[object, ...]
    shading_key: tuple[object, ...]
    transports: list[Transport] | None = None  # one per sample group (`LightStages.sample_groups`)
    images: torch.Tensor | None = None  # (2, N, 3) diffuse and specular unit images
    edited: int = 0  # when it was last set (`Relighter.edits`): the budget drops the oldest first
    progress: Progress | None = None  # `images` made so far, point by point, while they are None
    # Folded: its image is part of `MemoryBudget.folded` and its own images were dropped (the budget).
    folded: bool = False
    external: bool = False  # its images came from `set_unit_images`: they cannot be made again here
    # (N,) bool: points whose kept transport a material edit made stale, traced again when they are
    # next shaded (`LightStages.retrace_stale`); None: none.
    stale: torch.Tensor | None = None
