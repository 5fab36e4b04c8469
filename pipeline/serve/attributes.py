"""A light's USD attributes as JSON values, and edits of them checked before they reach the rig.

Attribute names are the UsdLux (and RelightBarzelLightAPI) names that `relight_torch.lights.usd`
reads and writes, taken from its one table (`light_inputs`), so a name the page shows is a name a
saved layer holds. Besides those inputs a light has:

- `xformOp:transform`: the world transform as USD writes it, a 4x4 row-vector matrix (rows of
  4 numbers, translation in the last row), since `write_light` authors it under `!resetXformStack!`;
- `relight:lightGroup`: the light-group AOV name;
- `ShapingAPI`, `RelightBarzelLightAPI`: whether the API schema is applied (setting one of its
  inputs applies it too, starting from its fallbacks).

Light and shadow links are shown but not editable here. Asset inputs (textures, cookies) take a
path inside the session's output directory or the shot's folder only.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import RelightError
from relight_torch.lights.emission import validate_light
from relight_torch.lights.image import read_linear_rgb
from relight_torch.lights.light import BarzelShaping, Light, LightKind, Shaping
from relight_torch.lights.usd import BARZEL_API, LIGHT_GROUP_ATTRIBUTE, LightInput, checked_value, light_inputs

TRANSFORM = "xformOp:transform"
SHAPING_API = "ShapingAPI"
_APIS = {SHAPING_API: ("shaping", Shaping), BARZEL_API: ("barzel", BarzelShaping)}
MAX_COORDINATE = 1e15
"""Largest |entry| of a light transform accepted: the relighter's geometry is float32 (3.4e38),
and squared distances of coordinates beyond ~1e19 overflow it; 1e15 leaves room for any scene."""


def attribute_checks(kind: LightKind) -> dict[str, str]:
    """Attribute name -> its check ('flag', 'finite', 'nonnegative', 'positive', 'colour', 'pair',
    'positive_pair', 'asset', plus 'matrix', 'string' and 'api' for the entries of the module doc)."""
    checks = {spec.attribute: spec.check for specs in light_inputs(kind).values() for spec in specs}
    return checks | {TRANSFORM: "matrix", LIGHT_GROUP_ATTRIBUTE: "string", SHAPING_API: "api", BARZEL_API: "api"}


def light_attributes(light: Light) -> dict[str, Any]:
    """Attribute name -> JSON value of a light (the inputs of its applied API schemas only)."""
    values: dict[str, Any] = {}
    for part, specs in light_inputs(light.kind).items():
        holder = light if part == "" else getattr(light, part)
        if holder is None:
            continue
        for spec in specs:
            value = getattr(holder, spec.field)
            values[spec.attribute] = list(value) if isinstance(value, tuple) else value
    values[TRANSFORM] = light.world_from_light.T.tolist()
    values[LIGHT_GROUP_ATTRIBUTE] = light.light_group
    values[SHAPING_API] = light.shaping is not None
    values[BARZEL_API] = light.barzel is not None
    return values


def edited_light(light: Light, values: dict[str, Any], asset_path: Callable[[str], Path]) -> Light:
    """`light` with the attribute `values` set, checked as a whole.

    Args:
        light: the light before the edit.
        values: attribute name -> JSON value (see the module doc).
        asset_path: turns a client's image path into a readable file it may open, raising
            RelightError otherwise (`SessionFiles.image_path`).

    Raises:
        RelightError: one line naming the light and attribute: an unknown attribute, a value of the
            wrong type, out of range or non-finite, or a light the renderer cannot honour.
    """
    if not isinstance(values, dict) or not values:
        raise RelightError(f"{light.path}: an edit is a JSON object of attribute values, got {values!r:.80}")
    checks = attribute_checks(light.kind)
    fields: dict[str, dict[str, Any]] = {"": {}, "shaping": {}, "shadow": {}, "barzel": {}}
    applied = {part: getattr(light, part) is not None for part, _ in _APIS.values()}
    for name, value in values.items():
        where = f"{light.path}: {name}"
        if name not in checks:
            raise RelightError(f"{where}: no such attribute on a {light.kind.value} (GET /api/session lists them)")
        if name in _APIS:
            if not isinstance(value, bool):
                raise RelightError(f"{where} = {value!r:.80} is not a bool")
            applied[_APIS[name][0]] = value
        elif name == TRANSFORM:
            fields[""]["world_from_light"] = _matrix(value, where)
        elif name == LIGHT_GROUP_ATTRIBUTE:
            if not isinstance(value, str) or not value.isprintable():
                raise RelightError(f"{where} = {value!r:.80} is not a printable string")
            fields[""]["light_group"] = value
        else:
            part, spec = _input(light.kind, name)
            fields[part].update(_field_values(spec, value, where, asset_path))
            if part in applied:
                applied[part] = True
    changes = fields[""]
    changes["shadow"] = dataclasses.replace(light.shadow, **fields["shadow"])
    for part, cls in _APIS.values():
        current = getattr(light, part)
        changes[part] = dataclasses.replace(current or cls(), **fields[part]) if applied[part] else None
    edited = dataclasses.replace(light, **changes)
    try:
        validate_light(edited)
    except ValueError as error:
        raise RelightError(str(error)) from None
    return edited


def _input(kind: LightKind, name: str) -> tuple[str, LightInput]:
    for part, specs in light_inputs(kind).items():
        for spec in specs:
            if spec.attribute == name:
                return part, spec
    raise KeyError(name)  # attribute_checks lists every input: unreachable for a checked name


def _field_values(spec: LightInput, value: Any, where: str, asset_path: Callable[[str], Path]) -> dict[str, Any]:
    """Field -> value of one input (an asset input also sets its decoded image)."""
    if spec.check != "asset":
        try:
            return {spec.field: checked_value(spec, value, where)}
        except ValueError as error:
            raise RelightError(str(error)) from None
    if not isinstance(value, str):
        raise RelightError(f"{where} = {value!r:.80} is not a path")
    image_field = "texture" if spec.field == "texture_file" else "cookie"
    if value == "":
        return {spec.field: "", image_field: None}
    path = asset_path(value)
    try:
        image = read_linear_rgb(str(path))
    except (OSError, ValueError, RuntimeError) as error:
        raise RelightError(f"{where}: cannot read image {value!r}: {str(error).splitlines()[0]}") from None
    return {spec.field: str(path), image_field: image}


def _matrix(value: Any, where: str) -> np.ndarray:
    """(4, 4) column-vector world_from_light from USD's row-vector rows; RelightError if malformed."""
    rows = value if isinstance(value, list) and len(value) == 4 else None
    if rows is None or not all(isinstance(row, list) and len(row) == 4 for row in rows):
        raise RelightError(f"{where}: a transform is 4 rows of 4 numbers")
    numbers = [x for row in rows for x in row]
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in numbers):
        raise RelightError(f"{where}: a transform holds numbers only")
    try:
        floats = [float(x) for x in numbers]
    except OverflowError:  # an integer beyond float range (JSON has no limit)
        floats = [math.inf]
    if not all(math.isfinite(x) and abs(x) <= MAX_COORDINATE for x in floats):
        raise RelightError(f"{where}: transform entries must be finite and within +-{MAX_COORDINATE:g}")
    matrix = np.array(floats, np.float64).reshape(4, 4).T
    if not np.allclose(matrix[3], (0.0, 0.0, 0.0, 1.0)):
        raise RelightError(f"{where}: the last column of a USD transform must be (0, 0, 0, 1)")
    if not abs(np.linalg.det(matrix[:3, :3])) > 1e-12 * max(1.0, float(np.abs(matrix[:3, :3]).max())) ** 3:
        raise RelightError(f"{where}: the transform is singular (a light needs three independent axes)")
    return matrix
