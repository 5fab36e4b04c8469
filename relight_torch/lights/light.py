"""Light parameters mirroring UsdLux 26.11 (and our Barzel-style applied schema).

These frozen dataclasses are THE light description of the project: the USD walker creates them,
the relighter and the reference renderer evaluate them (`relight_torch.lights.emission`), and
`relight_torch.lights.usd` writes them back to a USD layer. Their radiometric meaning is documented
once, in `relight_torch/lights/emission.py`.

Edit a light with `dataclasses.replace(light, intensity=...)`; a light is identified by `path`.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass, field

import numpy as np


class LightKind(enum.StrEnum):
    """The UsdLux light types, valued by their USD type names."""

    SPHERE = "SphereLight"
    DISTANT = "DistantLight"
    RECT = "RectLight"
    DISK = "DiskLight"
    CYLINDER = "CylinderLight"
    DOME = "DomeLight"


@dataclass(frozen=True)
class Shaping:
    """UsdLux ShapingAPI, present only when the API is applied (absent means no cone).

    cone_angle is the HALF-angle from the light's -Z axis, in degrees.
    """

    focus: float = 0.0
    focus_tint: tuple[float, float, float] = (0.0, 0.0, 0.0)
    cone_angle: float = 90.0
    cone_softness: float = 0.0


@dataclass(frozen=True)
class Shadow:
    """UsdLux ShadowAPI (fallbacks when not applied). distance/falloff -1 mean unlimited/none."""

    enable: bool = True
    color: tuple[float, float, float] = (0.0, 0.0, 0.0)
    distance: float = -1.0
    falloff: float = -1.0
    falloff_gamma: float = 1.0


@dataclass(frozen=True)
class BarzelShaping:
    """Our RelightBarzelLightAPI (relight_torch/schemas/schema.usda documents each attribute), present only when
    the API is applied. The fallbacks change nothing.

    Attributes:
        window_enable, window_width, window_height, window_edge, window_roundness: the
            superelliptical window on the plane one unit in front of the light (tangent units).
        barn_door_left, barn_door_right, barn_door_top, barn_door_bottom: flap angles in degrees
            from the -Z axis (180 = open).
        cookie_file: resolved cookie image path ('' for none); cookie: its (H, W, 3) float32 linear
            pixels (row 0 = top); cookie_scale, cookie_offset: its rectangle on the projected plane.
        near_start, near_end, far_start, far_end: world-space distance fall-off (near_end <= 0 /
            far_end < 0 turn a ramp off); falloff_smooth: smoothstep (True) or linear ramps.
    """

    window_enable: bool = False
    window_width: float = 1.0
    window_height: float = 1.0
    window_edge: float = 0.0
    window_roundness: float = 1.0
    barn_door_left: float = 180.0
    barn_door_right: float = 180.0
    barn_door_top: float = 180.0
    barn_door_bottom: float = 180.0
    cookie_file: str = ""
    cookie: np.ndarray | None = None
    cookie_scale: tuple[float, float] = (1.0, 1.0)
    cookie_offset: tuple[float, float] = (0.0, 0.0)
    near_start: float = 0.0
    near_end: float = 0.0
    far_start: float = -1.0
    far_end: float = -1.0
    falloff_smooth: bool = True


@dataclass(frozen=True)
class Light:
    """One UsdLux light at one time code.

    Attributes:
        path: the light prim's path; the key edits and links use.
        kind: the UsdLux type.
        world_from_light: (4, 4) float64 column-vector transform (scale included: normalize and
            area use world-space size).
        intensity, exposure, color, enable_color_temperature, color_temperature, normalize,
        diffuse, specular: the LightAPI inputs.
        radius: Sphere, Disk, Cylinder. width, height: Rect. length: Cylinder (along local X).
        angle: Distant, angular DIAMETER in degrees.
        treat_as_point / treat_as_line: hints only; see emission.py for what we do with them.
        texture_file: Rect or Dome texture path ('' for none); texture: its (H, W, 3) float32
            linear pixels (row 0 = top), loaded by the walker.
        shaping: ShapingAPI values or None when the API is not applied.
        shadow: ShadowAPI values.
        pole_axis: Dome only, 'Y' or 'Z': the resolved DomeLight_1 poleAxis (plain DomeLight: 'Y').
        barzel: RelightBarzelLightAPI values or None when the API is not applied.
        light_group: the light-group AOV this light writes to ('' = the prim's name; the USD reader
            always fills it in).
        light_link: object prim paths the light illuminates (its `collection:lightLink`), or
            None for every object (`relight_torch.lights.linking`).
        shadow_link: object prim paths that cast this light's shadows (`collection:shadowLink`),
            or None for every object.
    """

    path: str
    kind: LightKind
    world_from_light: np.ndarray = field(default_factory=lambda: np.eye(4))
    intensity: float = 1.0
    exposure: float = 0.0
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    enable_color_temperature: bool = False
    color_temperature: float = 6500.0
    normalize: bool = False
    diffuse: float = 1.0
    specular: float = 1.0
    radius: float = 0.5
    width: float = 1.0
    height: float = 1.0
    length: float = 1.0
    angle: float = 0.53
    treat_as_point: bool = False
    treat_as_line: bool = False
    texture_file: str = ""
    texture: np.ndarray | None = None
    shaping: Shaping | None = None
    shadow: Shadow = field(default_factory=Shadow)
    pole_axis: str = "Y"
    barzel: BarzelShaping | None = None
    light_group: str = ""
    light_link: tuple[str, ...] | None = None
    shadow_link: tuple[str, ...] | None = None


def light_snapshot(value: object) -> object:
    """A hashable, comparable snapshot of a light or a light field (arrays by content, dataclasses by field)."""
    if isinstance(value, np.ndarray):
        return value.shape, value.dtype.str, value.tobytes()
    if dataclasses.is_dataclass(value):
        return tuple((f.name, light_snapshot(getattr(value, f.name))) for f in dataclasses.fields(value))
    return value


def lights_equal(a: object, b: object) -> bool:
    """Whether two lights (or light fields) are equal: arrays by content, an array compared with
    itself without reading it (a light copied with `dataclasses.replace` shares its texture)."""
    if a is b:
        return True
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.shape == b.shape
            and a.dtype == b.dtype
            and bool(np.array_equal(a, b))
        )
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        fields = dataclasses.fields(a)
        return type(a) is type(b) and all(lights_equal(getattr(a, f.name), getattr(b, f.name)) for f in fields)
    return bool(a == b)
