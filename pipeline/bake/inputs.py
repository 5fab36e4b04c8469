"""What a bake read, hashed: the composed stage's layers and the texture files.

The cache records each input file with its sha256, so a later run can say exactly which input
changed (stale cache) instead of silently relighting old data. A layer or texture inside a .usdz
package is recorded as the package file (`shot.usdz[textures/a.png]` -> `shot.usdz`): that is
what is on disk, and what changes when anything inside it does.
"""

from __future__ import annotations

from pathlib import Path

from pxr import Ar

from pipeline.scene.types import Scene
from relight_torch.cache.layer import file_sha256
from relight_torch.stage import open_stage


def file_on_disk(path: str) -> str:
    """The file holding `path`: the outermost package for a package-relative path, else `path`."""
    return Ar.SplitPackageRelativePathOuter(path)[0] if Ar.IsPackageRelativePath(path) else path


def input_files(scene: Scene) -> list[str]:
    """Absolute paths of every file-backed layer of the shot and every texture the scene uses.

    Light-edit layers are not inputs: lights are applied at relight time.
    """
    stage = open_stage(scene.source)
    files = {file_on_disk(layer.realPath) for layer in stage.GetUsedLayers() if layer.realPath}
    for material in scene.materials:
        for value in vars(material).values():
            texture = getattr(value, "texture", None)
            if texture is not None and Path(file_on_disk(texture.file)).is_file():
                files.add(file_on_disk(texture.file))
    return sorted(str(Path(f).resolve()) for f in files)


def hash_inputs(files: list[str]) -> dict[str, str]:
    """path -> sha256 of its bytes."""
    return {f: file_sha256(f) for f in files}
