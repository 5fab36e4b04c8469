"""The project's bundled test/demo scenes, authored as real USD by the scripts in this package.

    SCENES['cornell_box'].write(directory) -> directory / 'cornell_box.usda'

`SCENES` maps a name to a `BundledScene` (name, camera prim path, description, write, example
light edits); `example_light_edits(name)` / `write_light_edits(name, directory)` give USD lights
layers over each scene for `--lights`. `LAYERED_SCENES` maps a name ('glossy+dome') to a
`LayeredScene`: a bundled scene with lights added by a lights layer (`layered_edit_layers`).
"""

from pipeline.scenes.bundled import BundledScene, LayeredScene, LightEdit, LightOverride
from pipeline.scenes.lights import example_light_edits, layered_edit_layers, light_edit_layers, write_light_edits
from pipeline.scenes.registry import LAYERED_SCENES, SCENES

__all__ = [
    "LAYERED_SCENES",
    "SCENES",
    "BundledScene",
    "LayeredScene",
    "LightEdit",
    "LightOverride",
    "example_light_edits",
    "layered_edit_layers",
    "light_edit_layers",
    "write_light_edits",
]
