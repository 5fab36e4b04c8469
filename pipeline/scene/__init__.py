"""Reading a USD shot into the in-memory `Scene` (see `types` for the data contract).

`load_scene`, `read_scene` and `find_camera` are imported on first use, so that importing the
types (or one scene module) does not pull in the whole walker and its dependencies.
"""

from pipeline.scene.types import Camera, Geometry, Material, MaterialInput, Scene, SceneObject, Texture

_LOAD_FUNCTIONS = ("find_camera", "load_scene", "read_scene")

__all__ = ["Camera", "Geometry", "Material", "MaterialInput", "Scene", "SceneObject", "Texture", *_LOAD_FUNCTIONS]


def __getattr__(name: str):
    if name in _LOAD_FUNCTIONS:
        from pipeline.scene import load

        return getattr(load, name)
    raise AttributeError(f"module 'pipeline.scene' has no attribute {name!r}")
