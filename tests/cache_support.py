"""Helpers shared by the cache tests (tests/test_cache*.py): small bakes of the bundled scenes."""

from __future__ import annotations

import shutil
from pathlib import Path

from pipeline.bake.direct.bake import bake_direct
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES

SIZE = 32


def bake_bundled(name: str, directory: Path, supersampling: int = 1) -> Path:
    """Write bundled scene `name` under directory/scene and bake a SIZE x SIZE cache into directory/cache.

    Returns:
        The cache layer's path.
    """
    shot = SCENES[name].write(directory / "scene")
    scene = load_scene(shot, width=SIZE, height=SIZE)
    camera = find_camera(scene, SCENES[name].camera)
    return bake_direct(scene, camera, directory / "cache", name, supersampling=supersampling, texture_samples=1)


def copy_bake(layer: Path, directory: Path) -> Path:
    """Copy a bake (its scene and cache folders, so relative paths hold) into `directory`; returns the copy's layer."""
    root = layer.parent.parent
    for folder in ("scene", "cache"):
        shutil.copytree(root / folder, directory / folder)
    return directory / "cache" / layer.name
