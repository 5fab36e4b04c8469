"""UsdLux prims to `Light` objects and back.

`read_light` reads one light prim at one time code (LightAPI inputs, the type's own inputs, the
ShapingAPI only where applied, the ShadowAPI, our RelightBarzelLightAPI, the world transform, and
the dome/rect texture and cookie images). `write_light` authors a `Light` so that reading it back
gives an equal `Light`: every input explicitly, and the world transform as one matrix op under
`!resetXformStack!`, so the light lands where it should whatever layer it is composed over.
Radiometric meaning: `relight_torch.lights.emission`.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

from relight_torch.io.atomic import atomic_path
from relight_torch.lights.emission import validate_light
from relight_torch.lights.image import read_linear_rgb
from relight_torch.lights.light import BarzelShaping, Light, LightKind, Shadow, Shaping
from relight_torch.lights.linking import read_link, write_link
from relight_torch.schema import register_schemas
from relight_torch.xform import world_from_local

log = logging.getLogger("relight")

BARZEL_API = "RelightBarzelLightAPI"
LIGHT_GROUP_ATTRIBUTE = "relight:lightGroup"

_KIND_FROM_TYPE = {
    "SphereLight": LightKind.SPHERE,
    "DistantLight": LightKind.DISTANT,
    "RectLight": LightKind.RECT,
    "DiskLight": LightKind.DISK,
    "CylinderLight": LightKind.CYLINDER,
    "DomeLight": LightKind.DOME,
    "DomeLight_1": LightKind.DOME,
}
_LATLONG_FORMATS = ("automatic", "latlong")
_FLOAT32_MAX = float(np.finfo(np.float32).max)


@dataclass(frozen=True)
class LightInput:
    """One USD attribute <-> one dataclass field, with the check its values must pass.

    check: 'flag' (bool), 'finite', 'nonnegative', 'positive', 'colour' (3 finite >= 0),
    'pair' (2 finite), 'positive_pair' (2 finite > 0), 'asset' (image file, '' for none).
    """

    field: str
    attribute: str
    check: str


_LIGHT_INPUTS = (
    LightInput("intensity", "inputs:intensity", "nonnegative"),
    LightInput("exposure", "inputs:exposure", "finite"),
    LightInput("color", "inputs:color", "colour"),
    LightInput("enable_color_temperature", "inputs:enableColorTemperature", "flag"),
    LightInput("color_temperature", "inputs:colorTemperature", "positive"),
    LightInput("normalize", "inputs:normalize", "flag"),
    LightInput("diffuse", "inputs:diffuse", "nonnegative"),
    LightInput("specular", "inputs:specular", "nonnegative"),
)
_KIND_INPUTS = {
    LightKind.SPHERE: (
        LightInput("radius", "inputs:radius", "nonnegative"),
        LightInput("treat_as_point", "treatAsPoint", "flag"),
    ),
    LightKind.RECT: (
        LightInput("width", "inputs:width", "nonnegative"),
        LightInput("height", "inputs:height", "nonnegative"),
        LightInput("texture_file", "inputs:texture:file", "asset"),
    ),
    LightKind.DISK: (LightInput("radius", "inputs:radius", "nonnegative"),),
    LightKind.CYLINDER: (
        LightInput("length", "inputs:length", "nonnegative"),
        LightInput("radius", "inputs:radius", "nonnegative"),
        LightInput("treat_as_line", "treatAsLine", "flag"),
    ),
    LightKind.DISTANT: (LightInput("angle", "inputs:angle", "nonnegative"),),
    LightKind.DOME: (LightInput("texture_file", "inputs:texture:file", "asset"),),
}
_SHAPING_INPUTS = (
    LightInput("focus", "inputs:shaping:focus", "finite"),
    LightInput("focus_tint", "inputs:shaping:focusTint", "colour"),
    LightInput("cone_angle", "inputs:shaping:cone:angle", "nonnegative"),
    LightInput("cone_softness", "inputs:shaping:cone:softness", "finite"),
)
_SHADOW_INPUTS = (
    LightInput("enable", "inputs:shadow:enable", "flag"),
    LightInput("color", "inputs:shadow:color", "colour"),
    LightInput("distance", "inputs:shadow:distance", "finite"),
    LightInput("falloff", "inputs:shadow:falloff", "finite"),
    LightInput("falloff_gamma", "inputs:shadow:falloffGamma", "nonnegative"),
)
_BARZEL_INPUTS = (
    LightInput("window_enable", "relight:barzel:window:enable", "flag"),
    LightInput("window_width", "relight:barzel:window:width", "positive"),
    LightInput("window_height", "relight:barzel:window:height", "positive"),
    LightInput("window_edge", "relight:barzel:window:edge", "finite"),
    LightInput("window_roundness", "relight:barzel:window:roundness", "nonnegative"),
    LightInput("barn_door_left", "relight:barzel:barnDoor:left", "nonnegative"),
    LightInput("barn_door_right", "relight:barzel:barnDoor:right", "nonnegative"),
    LightInput("barn_door_top", "relight:barzel:barnDoor:top", "nonnegative"),
    LightInput("barn_door_bottom", "relight:barzel:barnDoor:bottom", "nonnegative"),
    LightInput("cookie_file", "relight:barzel:cookie:file", "asset"),
    LightInput("cookie_scale", "relight:barzel:cookie:scale", "positive_pair"),
    LightInput("cookie_offset", "relight:barzel:cookie:offset", "pair"),
    LightInput("near_start", "relight:barzel:near:start", "finite"),
    LightInput("near_end", "relight:barzel:near:end", "finite"),
    LightInput("far_start", "relight:barzel:far:start", "finite"),
    LightInput("far_end", "relight:barzel:far:end", "finite"),
    LightInput("falloff_smooth", "relight:barzel:falloff:smooth", "flag"),
)


def light_inputs(kind: LightKind) -> dict[str, tuple[LightInput, ...]]:
    """The USD inputs a light of `kind` is read from and written to, by the part of `Light` they fill.

    Returns:
        '' (fields of `Light` itself), 'shaping' (`Light.shaping`), 'shadow' (`Light.shadow`) and
        'barzel' (`Light.barzel`) -> their inputs, in authoring order.
    """
    return {
        "": _LIGHT_INPUTS + _KIND_INPUTS[kind],
        "shaping": _SHAPING_INPUTS,
        "shadow": _SHADOW_INPUTS,
        "barzel": _BARZEL_INPUTS,
    }


def light_kind(prim: Usd.Prim) -> LightKind | None:
    """The `LightKind` of a light prim, or None for types we do not model (mesh, portal, ...)."""
    return _KIND_FROM_TYPE.get(str(prim.GetTypeName()))


def iter_light_prims(stage: Usd.Stage, time: Usd.TimeCode) -> Iterator[Usd.Prim]:
    """Every visible prim with UsdLux.LightAPI, instance proxies included, in namespace order.

    PointInstancer subtrees are pruned (their prototypes would light the scene at the prototype's
    own transform); invisible subtrees and non-render purposes are skipped.
    """
    prims = iter(Usd.PrimRange(stage.GetPseudoRoot(), Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
    for prim in prims:
        imageable = UsdGeom.Imageable(prim)
        if prim.IsA(UsdGeom.PointInstancer) or (
            imageable
            and (
                imageable.ComputeVisibility(time) == UsdGeom.Tokens.invisible
                or imageable.ComputePurpose() not in (UsdGeom.Tokens.default_, UsdGeom.Tokens.render)
            )
        ):
            prims.PruneChildren()
            continue
        if prim.HasAPI(UsdLux.LightAPI):
            yield prim


def read_light(prim: Usd.Prim, time: Usd.TimeCode = Usd.TimeCode.Default()) -> Light:
    """Read one UsdLux light prim.

    Args:
        prim: a SphereLight, DistantLight, RectLight, DiskLight, CylinderLight, DomeLight or
            DomeLight_1 prim (the schema plugin must be registered before its stage was opened).
        time: time code to read attributes and transforms at.

    Returns:
        The light; `texture` / `barzel.cookie` hold the decoded images, `light_group` defaults to
        the prim's name, `light_link` / `shadow_link` are the resolved link collections.

    Raises:
        ValueError: one line naming the prim and attribute, for an unsupported type, a non-finite or
            out-of-range value, a missing or unreadable image, or an unsupported transform.
    """
    kind = light_kind(prim)
    path = str(prim.GetPath())
    if kind is None:
        raise ValueError(
            f"{path}: unsupported light type '{prim.GetTypeName()}' (supported: {', '.join(_KIND_FROM_TYPE)})"
        )
    values = _read_inputs(prim, time, _LIGHT_INPUTS + _KIND_INPUTS[kind])
    if values.get("texture_file"):
        values["texture"] = read_linear_rgb(values["texture_file"])
    if kind is LightKind.DOME:
        values["pole_axis"] = _pole_axis(prim)
        texture_format = str(prim.GetAttribute("inputs:texture:format").Get(time))
        if values.get("texture_file") and texture_format not in _LATLONG_FORMATS:
            raise ValueError(
                f"{path}: inputs:texture:format '{texture_format}' is not supported "
                f"(only {' / '.join(_LATLONG_FORMATS)} lat-long maps)"
            )
    if prim.HasAPI(UsdLux.ShapingAPI):
        values["shaping"] = Shaping(**_read_inputs(prim, time, _SHAPING_INPUTS))
    values["shadow"] = Shadow(**_read_inputs(prim, time, _SHADOW_INPUTS))
    if prim.HasAPI(BARZEL_API):
        barzel = _read_inputs(prim, time, _BARZEL_INPUTS)
        if barzel.get("cookie_file"):
            barzel["cookie"] = read_linear_rgb(barzel["cookie_file"])
        values["barzel"] = BarzelShaping(**barzel)
    light_group = prim.GetAttribute(LIGHT_GROUP_ATTRIBUTE).Get(time) if prim.HasAttribute(LIGHT_GROUP_ATTRIBUTE) else ""
    light_api = UsdLux.LightAPI(prim)
    light = Light(
        path=path,
        kind=kind,
        world_from_light=_world_from_light(prim, time),
        light_group=light_group or prim.GetName(),
        light_link=read_link(light_api.GetLightLinkCollectionAPI()),
        shadow_link=read_link(light_api.GetShadowLinkCollectionAPI()),
        **values,
    )
    validate_light(light)
    return light


def _read_inputs(prim: Usd.Prim, time: Usd.TimeCode, inputs: tuple[LightInput, ...]) -> dict[str, Any]:
    """field -> checked value of every input that has a value (authored or schema fallback).

    Typed `Any`: each value's type follows its input's `check`, which the dataclass fields mirror.
    """
    values: dict[str, Any] = {}
    for spec in inputs:
        attribute = prim.GetAttribute(spec.attribute)
        value = attribute.Get(time) if attribute else None
        if value is not None:
            values[spec.field] = _checked(prim, spec, attribute, value, time)
    return values


def _checked(
    prim: Usd.Prim, spec: LightInput, attribute: Usd.Attribute, value: Any, time: Usd.TimeCode
) -> bool | str | float | tuple[float, ...]:
    """Convert a USD value to the dataclass field's Python type, raising ValueError when out of range."""
    where = f"{prim.GetPath()}: {spec.attribute}"
    stack = attribute.GetPropertyStack(time)
    authored = f"{where} = {value!r} (authored as {stack[0].typeName if stack else attribute.GetTypeName()})"
    if spec.check == "asset":
        if not isinstance(value, Sdf.AssetPath):
            raise ValueError(f"{authored} is not an asset path")
        return _resolve_asset(attribute, value, where, time)
    return checked_value(spec, value, where, authored)


def checked_value(spec: LightInput, value: Any, where: str, described: str = "") -> bool | float | tuple[float, ...]:
    """A flag or number input's value as its dataclass field's Python type (not 'asset' inputs).

    Args:
        spec: the input; its `check` says what the value must be.
        value: a bool, a number, or a sequence of numbers (USD's or JSON's).
        where: '<prim>: <attribute>', the start of the error message.
        described: how the value is named in a type error (default: where = value).

    Raises:
        ValueError: one line naming `where`, for a value of the wrong type, non-finite or out of range.
    """
    described = described or f"{where} = {value!r}"
    if spec.check == "flag":
        if not isinstance(value, (bool, int)):
            raise ValueError(f"{described} is not a bool")
        return bool(value)
    # A layer may author an input with another type than the schema's (a string, an int array):
    # refused here, not left to fail in a conversion below.
    count = {"colour": 3, "pair": 2, "positive_pair": 2}.get(spec.check, 1)
    items = [value] if count == 1 else (list(value) if hasattr(value, "__len__") and not isinstance(value, str) else [])
    if len(items) != count or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in items):
        raise ValueError(f"{described} is not {'a number' if count == 1 else f'{count} numbers'}")
    try:
        numbers = tuple(float(x) for x in items)
    except OverflowError:  # an integer beyond float range (JSON has no limit)
        numbers = (math.inf,)
    # Light inputs are floats in the schema: a double authored beyond float32's range (1e300) is
    # finite here but inf in every kernel.
    if any(math.isfinite(x) and abs(x) > _FLOAT32_MAX for x in numbers):
        raise ValueError(f"{described} overflows a float (the schema's type, largest {_FLOAT32_MAX:.4g})")
    minimum, strict = {
        "nonnegative": (0.0, False),
        "colour": (0.0, False),
        "positive": (0.0, True),
        "positive_pair": (0.0, True),
    }.get(spec.check, (-math.inf, False))
    if not all(math.isfinite(x) and (x > minimum if strict else x >= minimum) for x in numbers):
        bound = "" if minimum == -math.inf else f" and {'>' if strict else '>='} {minimum:g}"
        raise ValueError(f"{where} = {value} must be finite{bound}")
    return numbers if len(numbers) > 1 else numbers[0]


def _resolve_asset(attribute: Usd.Attribute, value: Sdf.AssetPath, where: str, time: Usd.TimeCode) -> str:
    """Absolute path of an authored image asset ('' when empty); ValueError when the file is missing."""
    if not value.path:
        return ""
    resolved: str = value.resolvedPath
    if not resolved:
        layer = attribute.GetPropertyStack(time)[0].layer
        resolved = Sdf.ComputeAssetPathRelativeToLayer(layer, value.path)
    if not os.path.isfile(resolved):
        raise ValueError(f"{where}: image '{value.path}' not found")
    return os.path.abspath(resolved)


def _pole_axis(prim: Usd.Prim) -> str:
    """'Y' or 'Z': DomeLight_1's poleAxis with 'scene' resolved to the stage's up axis; DomeLight: 'Y'."""
    if prim.GetTypeName() != "DomeLight_1":
        return "Y"
    pole_axis = str(UsdLux.DomeLight_1(prim).GetPoleAxisAttr().Get())
    return str(UsdGeom.GetStageUpAxis(prim.GetStage())) if pole_axis == "scene" else pole_axis


def _world_from_light(prim: Usd.Prim, time: Usd.TimeCode) -> np.ndarray:
    """(4, 4) float64 column-vector world_from_light; ValueError if not finite and invertible."""
    world_from_light = world_from_local(UsdGeom.XformCache(time), prim)
    if not np.isfinite(world_from_light).all() or abs(np.linalg.det(world_from_light[:3, :3])) < 1e-300:
        raise ValueError(f"{prim.GetPath()}: world transform is not finite and invertible")
    return world_from_light


def write_light(stage: Usd.Stage, light: Light) -> Usd.Prim:
    """Author `light` on the stage's edit target at the default time.

    Every input of the light's type is authored (also where it equals the fallback, so that the
    layer overrides whatever it is composed over); ShapingAPI and RelightBarzelLightAPI are applied
    when present and deleted (a `delete` list-op entry) when absent, so a lights layer removes them
    from the shot below. Fields that do not belong to the light's type (say `width` on a sphere)
    are not written.

    Args:
        stage: the stage to author on (the schema plugin registered before it was opened).
        light: the light; `light.path` is where it is defined.

    Returns:
        The light prim.
    """
    type_name = "DomeLight_1" if light.kind is LightKind.DOME and light.pole_axis != "Y" else light.kind.value
    prim = stage.DefinePrim(light.path, type_name)
    _write_inputs(prim, light, _LIGHT_INPUTS + _KIND_INPUTS[light.kind])
    if light.kind is LightKind.DOME:
        if light.texture_file:
            prim.GetAttribute("inputs:texture:format").Set("latlong")
        if type_name == "DomeLight_1":
            UsdLux.DomeLight_1(prim).CreatePoleAxisAttr(light.pole_axis)
    applied = {"ShapingAPI": light.shaping is not None, "ShadowAPI": True, BARZEL_API: light.barzel is not None}
    _author_api_schemas(prim, applied)
    for values, inputs in (
        (light.shaping, _SHAPING_INPUTS),
        (light.shadow, _SHADOW_INPUTS),
        (light.barzel, _BARZEL_INPUTS),
    ):
        if values is not None:
            _write_inputs(prim, values, inputs)
    light_api = UsdLux.LightAPI(prim)
    write_link(light_api.GetLightLinkCollectionAPI(), light.light_link)
    write_link(light_api.GetShadowLinkCollectionAPI(), light.shadow_link)
    if light.light_group:
        prim.CreateAttribute(LIGHT_GROUP_ATTRIBUTE, Sdf.ValueTypeNames.String).Set(light.light_group)
    xformable = UsdGeom.Xformable(prim)
    xformable.MakeMatrixXform().Set(Gf.Matrix4d(light.world_from_light.T.tolist()))
    xformable.SetResetXformStack(True)
    return prim


def _author_api_schemas(prim: Usd.Prim, applied: dict[str, bool]) -> None:
    """Prepend the applied API schemas and delete the others in the edit target's `apiSchemas`.

    The `delete` entries make a lights layer override the shot it is composed over (a light whose
    ShapingAPI was removed loses it); API schemas we do not manage are kept as authored.
    """
    spec = prim.GetStage().GetEditTarget().GetPrimSpecForScenePath(prim.GetPath())
    current = spec.GetInfo("apiSchemas") if spec.HasInfo("apiSchemas") else Sdf.TokenListOp()

    def unmanaged(items: Iterable[str]) -> list[str]:
        return [item for item in items if item not in applied]

    wanted = [name for name, on in applied.items() if on]
    if current.isExplicit:
        operation = Sdf.TokenListOp.CreateExplicit(unmanaged(current.explicitItems) + wanted)
    else:
        operation = Sdf.TokenListOp.Create(
            prependedItems=unmanaged(current.prependedItems) + wanted,
            appendedItems=unmanaged(current.appendedItems),
            deletedItems=unmanaged(current.deletedItems) + [name for name, on in applied.items() if not on],
        )
    spec.SetInfo("apiSchemas", operation)


def _write_inputs(prim: Usd.Prim, values: object, inputs: tuple[LightInput, ...]) -> None:
    """Author each input's attribute from the same-named field of `values` (a dataclass)."""
    for spec in inputs:
        value = getattr(values, spec.field)
        prim.GetAttribute(spec.attribute).Set(Sdf.AssetPath(value) if spec.check == "asset" else value)


def read_stage_lights(stage: Usd.Stage, time: Usd.TimeCode, warnings: list[str] | None = None) -> list[Light]:
    """Read every visible light of a stage (see `iter_light_prims`) at `time`.

    Lights of unsupported types are skipped, and light filters and dome portals ignored, each with
    a one-line warning logged on the 'relight' logger and appended to `warnings` when given.

    Raises:
        ValueError: a light is invalid (see `read_light`).
    """
    lights = []
    for prim in iter_light_prims(stage, time):
        problems = []
        if light_kind(prim) is None:
            problems.append(f"{prim.GetPath()}: light type '{prim.GetTypeName()}' is not supported; skipped")
        elif UsdLux.LightAPI(prim).GetFiltersRel().GetTargets():
            problems.append(f"{prim.GetPath()}: light:filters are not supported; ignored")
        if prim.HasRelationship("portals") and prim.GetRelationship("portals").GetTargets():
            problems.append(f"{prim.GetPath()}: dome light portals are not supported; ignored")
        for message in problems:
            log.warning(message)
            if warnings is not None:
                warnings.append(message)
        if light_kind(prim) is not None:
            lights.append(read_light(prim, time))
    return lights


def read_lights_layer(path: str | os.PathLike[str]) -> list[Light]:
    """Read every supported light of a USD layer (e.g. one written by `write_lights_layer`).

    Raises:
        ValueError: the layer cannot be opened, or a light is invalid (see `read_light`).
    """
    register_schemas()
    try:
        stage = Usd.Stage.Open(os.fspath(path))
    except Exception as error:  # pxr raises Tf.ErrorException with a multi-line message
        raise ValueError(f"{path}: cannot open USD layer ({str(error).splitlines()[-1].strip()})") from None
    return read_stage_lights(stage, Usd.TimeCode.Default())


def write_lights_layer(path: str | os.PathLike[str], lights: list[Light]) -> None:
    """Write `lights` to a new USD layer at `path` atomically (temp file, then rename).

    Each light keeps its world transform (`!resetXformStack!`), so the layer can be composed as the
    strongest sublayer over its shot. The root prim is the default prim when the lights share one.
    """
    register_schemas()
    stage = Usd.Stage.CreateInMemory()
    for light in lights:
        write_light(stage, light)
    roots = {Sdf.Path(light.path).GetPrefixes()[0] for light in lights}
    if len(roots) == 1:
        stage.SetDefaultPrim(stage.GetPrimAtPath(roots.pop()))
    with atomic_path(path) as temp:
        if not stage.GetRootLayer().Export(os.fspath(temp)):
            raise OSError(f"{path}: could not write the lights layer")
