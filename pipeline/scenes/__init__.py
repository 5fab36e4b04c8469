"""The project's bundled test/demo scenes, authored as real USD by the scripts in this package.

    SCENES['cornell_box'].write(directory) -> directory / 'cornell_box.usda'

`SCENES` maps a name to a `BundledScene` (name, camera prim path, description, write, example
light edits); `example_light_edits(name)` / `write_light_edits(name, directory)` give USD lights
layers over each scene for `--lights`.
"""

from pipeline.scenes.bundled import BundledScene, LightEdit, LightOverride
from pipeline.scenes.lights import example_light_edits, light_edit_layers, write_light_edits
from pipeline.scenes.registry import SCENES

__all__ = [
    "SCENES",
    "BundledScene",
    "LightEdit",
    "LightOverride",
    "example_light_edits",
    "light_edit_layers",
    "write_light_edits",
]
