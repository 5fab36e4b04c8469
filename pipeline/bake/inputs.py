"""What a bake read, hashed: the composed stage's layers and the texture files (and what it was
asked for: a re-run of the same request on unchanged inputs finds its cache up to date).

The cache records each input file with its sha256, so a later run can say exactly which input
changed (stale cache) instead of silently relighting old data. A layer or texture inside a .usdz
package is recorded as the package file (`shot.usdz[textures/a.png]` -> `shot.usdz`): that is
what is on disk, and what changes when anything inside it does.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
from pathlib import Path

from pxr import Ar

import pipeline
import relight_torch
from pipeline.scene.types import Scene
from relight_torch.cache.layer import content_hash, file_sha256, read_cache_layer, write_cache_layer
from relight_torch.cache.status import cache_status
from relight_torch.errors import RelightError
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
        files.update(document for document in material.documents if Path(document).is_file())
        for value in vars(material).values():
            texture = getattr(value, "texture", None)
            if texture is not None and Path(file_on_disk(texture.file)).is_file():
                files.add(file_on_disk(texture.file))
    return sorted(str(Path(f).resolve()) for f in files)


CODE_VERSION_VARIABLE = "RELIGHT_CODE_VERSION"


def code_version() -> str:
    """The code version a bake records and hashes: $RELIGHT_CODE_VERSION when set (a farm's
    release tag, the same on every worker), else '<package version>+<digest>' with the digest
    (16 hex) over the sources of `pipeline` and `relight_torch`, so that chunks and content hashes
    change with any code that could change a result, not only with the version number."""
    return os.environ.get(CODE_VERSION_VARIABLE) or f"{pipeline.__version__}+{_source_digest()}"


@functools.lru_cache(maxsize=1)
def _source_digest() -> str:
    digest = hashlib.sha256()
    for package in (pipeline, relight_torch):
        root = Path(package.__file__).parent
        for source in sorted(root.rglob("*.py")):
            digest.update(f"{source.relative_to(root.parent)}\0".encode())
            digest.update(source.read_bytes())
    return digest.hexdigest()[:16]


def hash_inputs(files: list[str]) -> dict[str, str]:
    """path -> sha256 of its bytes."""
    return {f: file_sha256(f) for f in files}


REQUEST_PARAMETER = "request"
"""Cache-layer parameter holding `request_digest` of the bake command that wrote the cache."""


def request_digest(request: dict) -> str:
    """sha256 (16 hex) of a bake request (the command's options that shape the cache) and the code
    version: equal digests over unchanged inputs make the same cache."""
    text = json.dumps({**request, "codeVersion": code_version()}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def up_to_date(layer_path: Path, digest: str) -> bool:
    """Whether the cache at `layer_path` was baked for request `digest` and is still valid: every
    payload as recorded and no input changed since."""
    if not layer_path.is_file():
        return False
    try:
        status = cache_status(layer_path)
    except RelightError:
        return False
    return status.description.parameters.get(REQUEST_PARAMETER) == digest and status.verdict == "valid"


def record_request(layer_path: Path, digest: str) -> None:
    """Add `digest` to the cache layer's parameters (rewritten atomically), its content hash
    recomputed so that it still covers every recorded parameter."""
    description = read_cache_layer(layer_path)
    parameters = {**description.parameters, REQUEST_PARAMETER: digest}
    write_cache_layer(
        layer_path,
        dataclasses.replace(
            description,
            parameters=parameters,
            content_hash=content_hash(description.inputs, parameters, description.code_version),
        ),
    )


def identify_bake(scene: Scene, parameters: dict, time_code: float | None) -> tuple[dict, dict[str, str], str]:
    """What a bake records about itself: its parameters (plus 'time' when a time code is given),
    its hashed input files and its content hash over both and the code version."""
    if time_code is not None:
        parameters = {**parameters, "time": float(time_code)}
    inputs = hash_inputs(input_files(scene))
    return parameters, inputs, content_hash(inputs, parameters, code_version())
