"""The registry of bundled scenes, by name."""

from pipeline.scenes import cornell_box, dome, glossy, leaves
from pipeline.scenes import set as set_scene
from pipeline.scenes.bundled import BundledScene, LayeredScene

SCENES: dict[str, BundledScene] = {
    scene.name: scene for scene in (cornell_box.SCENE, glossy.SCENE, set_scene.SCENE, dome.SCENE, leaves.SCENE)
}
LAYERED_SCENES: dict[str, LayeredScene] = {scene.name: scene for scene in (dome.GLOSSY_DOME,)}
"""Bundled scenes with lights added by a lights layer, by name."""
