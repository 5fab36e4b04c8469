"""The registry of bundled scenes, by name."""

from pipeline.scenes import cornell_box, dome, glossy, leaves
from pipeline.scenes import set as set_scene
from pipeline.scenes.bundled import BundledScene

SCENES: dict[str, BundledScene] = {
    scene.name: scene for scene in (cornell_box.SCENE, glossy.SCENE, set_scene.SCENE, dome.SCENE, leaves.SCENE)
}
