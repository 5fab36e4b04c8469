"""A lights layer holding only what changed: the rig before an edit session against the rig after.

`relight serve` saves a session with it and `relight solve` writes its solved rig with it; `relight
render CACHE --lights LAYER` composes the layer as the strongest sublayer over the shot, so the
result is the edited rig exactly. Each light is authored with `write_light` twice (before and
after) in scratch layers and the two prim specs are compared, so the layer's attribute names,
types and transform are the ones `write_light` authors and `read_light` reads back:

- a light only in `after` is defined whole (`def`);
- a light in both is an `over` holding the attributes, relationships and `apiSchemas` whose
  authored value changed (a moved light: its `xformOp:transform` and `xformOpOrder`);
- a light only in `before` is deactivated (`over` with `active = false`), since a stronger layer
  cannot delete a prim defined in a weaker one.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

from pxr import Sdf, Usd

from relight_torch.io.atomic import atomic_path
from relight_torch.lights.light import Light
from relight_torch.lights.usd import write_light
from relight_torch.schema import register_schemas


def light_overrides_layer(before: Sequence[Light], after: Sequence[Light]) -> Sdf.Layer:
    """An anonymous layer with the changes from rig `before` to rig `after` (lights matched by path).

    Raises:
        ValueError: two lights of one rig share a prim path.
    """
    register_schemas()
    old, new = _by_path(before, "before"), _by_path(after, "after")
    layer = Sdf.Layer.CreateAnonymous(".usda")
    for path, light in new.items():
        if path not in old:
            _define(layer, light)
        else:
            _override_changes(layer, old[path], light)
    for path in old.keys() - new.keys():
        spec = Sdf.CreatePrimInLayer(layer, path)
        spec.specifier = Sdf.SpecifierOver
        spec.active = False
    return layer


def write_light_overrides(path: str | os.PathLike[str], before: Sequence[Light], after: Sequence[Light]) -> None:
    """Write `light_overrides_layer(before, after)` to `path` atomically (`export_layer`)."""
    export_layer(path, light_overrides_layer(before, after))


def export_layer(path: str | os.PathLike[str], layer: Sdf.Layer) -> None:
    """Write `layer` to `path` (its format from the suffix) atomically: temp file, then rename.

    Raises:
        OSError: the file could not be written (disk full, permissions), naming `path`.
    """
    with atomic_path(path) as temp:
        if not layer.Export(os.fspath(temp)):
            raise OSError(f"{path}: could not write the layer")


def _by_path(lights: Sequence[Light], role: str) -> dict[str, Light]:
    rig: dict[str, Light] = {}
    for light in lights:
        if light.path in rig:
            raise ValueError(f"{light.path}: two lights of the {role} rig share this prim path")
        rig[light.path] = light
    return rig


def _authored(light: Light) -> Sdf.Layer:
    """A scratch layer holding what `write_light` authors for `light` (its prim specs expire with it)."""
    layer = Sdf.Layer.CreateAnonymous(".usda")
    write_light(Usd.Stage.Open(layer), light)
    return layer


def _define(layer: Sdf.Layer, light: Light) -> None:
    source = _authored(light)
    Sdf.CreatePrimInLayer(layer, light.path)
    Sdf.CopySpec(source, Sdf.Path(light.path), layer, Sdf.Path(light.path))


def _override_changes(layer: Sdf.Layer, before: Light, after: Light) -> None:
    """Author an `over` of `after.path` holding what differs between the two authored specs."""
    old_layer, new_layer = _authored(before), _authored(after)
    old, new = old_layer.GetPrimAtPath(Sdf.Path(before.path)), new_layer.GetPrimAtPath(Sdf.Path(after.path))
    if old.typeName != new.typeName:  # a light changed type: a new definition replaces it
        _define(layer, after)
        return
    changed = [
        name
        for name, spec in new.properties.items()
        if name not in old.properties or not _same_property(old.properties[name], spec)
    ]
    if any(name.startswith("xformOp:") for name in changed):
        # the shot's own op order (a translate, a rotate...) would ignore the new matrix op
        changed.append("xformOpOrder")
    schemas_changed = new.GetInfo("apiSchemas") != old.GetInfo("apiSchemas")
    if not changed and not schemas_changed:
        return
    spec = Sdf.CreatePrimInLayer(layer, after.path)
    spec.specifier = Sdf.SpecifierOver
    if schemas_changed:
        spec.SetInfo("apiSchemas", new.GetInfo("apiSchemas"))
    for name in changed:
        Sdf.CopySpec(new_layer, new.path.AppendProperty(name), layer, spec.path.AppendProperty(name))


def _same_property(old: Sdf.PropertySpec, new: Sdf.PropertySpec) -> bool:
    if isinstance(new, Sdf.RelationshipSpec):
        return isinstance(old, Sdf.RelationshipSpec) and list(old.targetPathList.GetAddedOrExplicitItems()) == list(
            new.targetPathList.GetAddedOrExplicitItems()
        )
    return (
        isinstance(old, Sdf.AttributeSpec)
        and old.typeName == new.typeName
        and old.default == new.default
        and old.GetInfo("variability") == new.GetInfo("variability")
    )
