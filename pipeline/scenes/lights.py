"""Example light edits over the bundled scenes, as USD layers that `--lights` composes.

A lights layer holds only `over`s of the scene's light prims: composed as the strongest sublayer
(see `pipeline.scene.stage.open_stage`), its opinions replace the scene's for the attributes it
names and leave the rest alone. Each scene lists its edits in `BundledScene.light_edits`.
"""

from __future__ import annotations

from pathlib import Path

from pxr import Sdf, Usd

from pipeline.errors import RelightError
from pipeline.scenes.bundled import LightEdit
from pipeline.scenes.registry import SCENES
from relight_torch.io.atomic import write_text_atomic
from relight_torch.schema import register_schemas


def edit_layer_text(scene_name: str, edit: LightEdit) -> str:
    """The .usda text of one light edit: `over`s of the edited lights with their new values."""
    register_schemas()
    stage = Usd.Stage.CreateInMemory()
    stage.GetRootLayer().documentation = f"Light edit '{edit.name}' over bundled scene '{scene_name}': {edit.description}"
    for override in edit.overrides:
        prim = stage.OverridePrim(override.prim_path)
        for api in override.api_schemas:
            prim.AddAppliedSchema(api)
        for attribute, (type_name, value) in override.values.items():
            value_type = Sdf.ValueTypeNames.Find(type_name)
            prim.CreateAttribute(attribute, value_type, custom=False).Set(value)
    return stage.GetRootLayer().ExportToString()


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
