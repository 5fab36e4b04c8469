"""Example light edits over the bundled scenes, as USD layers that `--lights` composes.

A lights layer holds only `over`s of the scene's light prims: composed as the strongest sublayer
(see `pipeline.scene.stage.open_stage`), its opinions replace the scene's for the attributes it
names and leave the rest alone. Each scene lists its edits in `BundledScene.light_edits`. A
`LayeredScene`'s layer adds lights; its edits sublayer it, so that one `--lights` layer carries both.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

from pipeline.errors import RelightError
from pipeline.scenes.bundled import LightEdit
from pipeline.scenes.registry import LAYERED_SCENES, SCENES
from relight_torch.io.atomic import write_text_atomic
from relight_torch.schema import register_schemas

NEW_LIGHT_PATH = "/RelightEdits/AddedSphere"
"""The prim of the light `new_sphere_layer` adds."""


def edit_layer_text(scene_name: str, edit: LightEdit, over: Path | None = None) -> str:
    """The .usda text of one light edit: `over`s of the edited lights with their new values, over
    the lights layer `over` (a sublayer by its file name: the edit is written beside it) if given."""
    register_schemas()
    stage = Usd.Stage.CreateInMemory()
    stage.GetRootLayer().documentation = (
        f"Light edit '{edit.name}' over bundled scene '{scene_name}': {edit.description}"
    )
    for override in edit.overrides:
        prim = stage.OverridePrim(override.prim_path)
        for api in override.api_schemas:
            prim.AddAppliedSchema(api)
        for attribute, (type_name, value) in override.values.items():
            value_type = Sdf.ValueTypeNames.Find(type_name)
            prim.CreateAttribute(attribute, value_type, custom=False).Set(value)
    return _over(stage.GetRootLayer(), over)


def _over(layer: Sdf.Layer, over: Path | None) -> str:
    """`layer`'s .usda text, with `over` as its sublayer (by file name) if given. The sublayer goes
    on a detached copy: a stage of the in-memory layer could not resolve the relative path."""
    if over is None:
        return layer.ExportToString()
    detached = Sdf.Layer.CreateAnonymous(".usda")
    detached.TransferContent(layer)
    detached.subLayerPaths.append(f"./{over.name}")
    return detached.ExportToString()


def _scene(name: str):
    if name not in SCENES:
        raise RelightError(f"unknown bundled scene {name!r}; choose one of {', '.join(SCENES)}")
    return SCENES[name]


def example_light_edits(name: str) -> list[tuple[str, str]]:
    """(edit name, lights-layer .usda text) for each example light edit of bundled scene `name`."""
    return [(edit.name, edit_layer_text(name, edit)) for edit in _scene(name).light_edits]


def write_light_edits(name: str, directory: str | Path) -> list[Path]:
    """Write DIR/<scene>.lights.<edit>.usda for every example edit of scene `name`; return the paths."""
    paths = []
    for edit_name, text in example_light_edits(name):
        path = Path(directory) / f"{name}.lights.{edit_name}.usda"
        write_text_atomic(path, text)
        paths.append(path)
    return paths


def light_edit_layers(name: str, directory: str | Path) -> dict[str, Path | None]:
    """'shot' -> None (the shot's own lights), then each example edit's name -> its layer written
    by `write_light_edits`: the light edits every benchmark relights under."""
    return {"shot": None} | {path.name.split(".")[-2]: path for path in write_light_edits(name, directory)}


def layered_edit_layers(name: str, directory: str | Path) -> dict[str, Path]:
    """'shot' -> the lights layer of `LAYERED_SCENES[name]` (written with its base scene into
    `directory`), then each example edit's name -> DIR/<name>.lights.<edit>.usda, authored over it."""
    if name not in LAYERED_SCENES:
        raise RelightError(f"unknown layered scene {name!r}; choose one of {', '.join(LAYERED_SCENES)}")
    layered = LAYERED_SCENES[name]
    base = layered.write_layer(Path(directory))
    layers = {"shot": base}
    for edit in layered.light_edits:
        path = Path(directory) / f"{name}.lights.{edit.name}.usda"
        write_text_atomic(path, edit_layer_text(name, edit, over=base))
        layers[edit.name] = path
    return layers


def new_sphere_layer(scene_path: Path, camera_path: str, out: Path, over: Path | None = None) -> Path:
    """A lights layer adding a small sphere light between the camera and the scene's centre, over
    the lights layer `over` (a sublayer by file name: `out` goes beside it) if given.

    It sits 30 % of the way from the camera to the centre of the scene's bounds, with a radius of 2 %
    of their diagonal and a radiance giving an irradiance of about 0.5 at the centre.
    """
    stage = Usd.Stage.Open(str(scene_path))
    bounds = (
        UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default", "render"])
        .ComputeWorldBound(stage.GetPseudoRoot())
        .ComputeAlignedRange()
    )
    centre, diagonal = np.array(bounds.GetMidpoint()), float(bounds.GetSize().GetLength())
    camera = UsdGeom.Camera(stage.GetPrimAtPath(camera_path)).GetCamera(Usd.TimeCode.Default())
    eye = np.array(camera.frustum.GetPosition())
    position = eye + 0.3 * (centre - eye)
    radius = 0.02 * diagonal
    distance = max(float(np.linalg.norm(centre - position)), radius * 2.0)
    layer_stage = Usd.Stage.CreateInMemory()
    light = UsdLux.SphereLight.Define(layer_stage, NEW_LIGHT_PATH)
    light.CreateRadiusAttr(radius)
    light.CreateIntensityAttr(float(0.5 / (np.pi * (radius / distance) ** 2)))
    light.CreateColorAttr(Gf.Vec3f(1.0, 0.85, 0.7))
    UsdGeom.Xformable(light).AddTranslateOp().Set(Gf.Vec3d(*position.tolist()))
    write_text_atomic(out, _over(layer_stage.GetRootLayer(), over))
    return out
