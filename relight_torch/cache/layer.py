"""The cache layer: `<stem>.relight.usda`, authored with our codeless schema (`schemas/`).

    def RelightCache "Cache"            method, version, source stage, camera, resolution,
        matrix4d relight:worldFromCamera    supersampling, content hash, the inputs and their hashes,
        relight:parameters:<name> = ...     the method's parameters (one typed attribute each)
        def RelightPayload "<name>"     one per payload file: relative path, format, sha256, bytes,
                                            EXR channels or .npy shape and dtype, and the channels
                                            elided because constant (name + value)

Payload files sit beside the layer and are referenced by relative asset paths. Nothing here is
pickled; writes are atomic (temp file, then rename).
"""

from __future__ import annotations

import hashlib
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, Vt

from relight_torch.errors import RelightError
from relight_torch.io.atomic import atomic_path
from relight_torch.schema import register_schemas

CACHE_PRIM = "/Cache"
CACHE_VERSION = 1
SUFFIX = ".relight.usda"


@dataclass(frozen=True)
class Payload:
    """One payload file of a cache.

    Attributes:
        name: prim name (e.g. 'deepFramebuffer').
        file: path relative to the cache layer's directory.
        format: 'exr' or 'npy'.
        sha256: hex digest of the file's bytes.
        num_bytes: file size.
        channels: EXR channel names (exr) — empty for npy.
        shape, dtype: array shape and numpy dtype name (npy) — empty for exr.
        constants: channel name -> value, for channels elided because constant over the image.
    """

    name: str
    file: str
    format: str
    sha256: str
    num_bytes: int
    channels: tuple[str, ...] = ()
    shape: tuple[int, ...] = ()
    dtype: str = ""
    constants: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class CacheDescription:
    """Everything the cache layer records.

    Attributes:
        method: 'direct', 'transfer', 'gather', 'cuts' or 'multiview'.
        source: the shot's root layer, as an absolute path (stored relative to the layer).
        camera_path: the camera prim the cache was baked from.
        resolution: (width, height) in pixels.
        supersampling: sub-samples per pixel side.
        world_from_camera: (4, 4) float64 column-vector transform.
        exposure_scale: the camera's linear exposure scale, applied to relit images.
        content_hash: sha256 over every input hash and the parameters.
        inputs: input file (absolute path) -> sha256 of its bytes.
        parameters: the method's parameters (bool, int, float or str values).
        payloads: the payload files.
    """

    method: str
    source: str
    camera_path: str
    resolution: tuple[int, int]
    supersampling: int
    world_from_camera: np.ndarray
    exposure_scale: float
    content_hash: str
    inputs: dict[str, str]
    parameters: dict[str, bool | int | float | str]
    payloads: tuple[Payload, ...]

    def payload(self, name: str) -> Payload:
        for payload in self.payloads:
            if payload.name == name:
                return payload
        raise RelightError(f"cache has no payload named {name!r} (has {[p.name for p in self.payloads]})")


def file_sha256(path: str | os.PathLike) -> str:
    """Hex sha256 of a file's bytes, read in 1 MB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def content_hash(inputs: dict[str, str], parameters: dict[str, object], code_version: str) -> str:
    """One sha256 over the input hashes (sorted by path), the parameters and the code version."""
    digest = hashlib.sha256(code_version.encode())
    for path in sorted(inputs):
        digest.update(f"{path}\0{inputs[path]}\0".encode())
    for name in sorted(parameters):
        digest.update(f"{name}\0{parameters[name]!r}\0".encode())
    return digest.hexdigest()


def _sdf_type(value) -> Sdf.ValueTypeName:
    if isinstance(value, bool):
        return Sdf.ValueTypeNames.Bool
    if isinstance(value, int):
        return Sdf.ValueTypeNames.Int64
    if isinstance(value, float):
        return Sdf.ValueTypeNames.Double
    if isinstance(value, str):
        return Sdf.ValueTypeNames.String
    raise TypeError(f"cache parameter of unsupported type {type(value).__name__}: {value!r}")


def write_cache_layer(path: str | os.PathLike, description: CacheDescription) -> None:
    """Author the cache layer atomically. Payload files must already be written beside it."""
    register_schemas()
    path = Path(path)
    directory = path.parent.resolve()
    layer = Sdf.Layer.CreateAnonymous(SUFFIX)
    stage = Usd.Stage.Open(layer)
    cache = stage.DefinePrim(CACHE_PRIM, "RelightCache")
    stage.SetDefaultPrim(cache)
    cache.GetAttribute("relight:method").Set(description.method)
    cache.GetAttribute("relight:version").Set(CACHE_VERSION)
    cache.GetAttribute("relight:source").Set(Sdf.AssetPath(os.path.relpath(description.source, directory)))
    cache.GetAttribute("relight:cameraPath").Set(description.camera_path)
    cache.GetAttribute("relight:resolution").Set(Gf.Vec2i(*description.resolution))
    cache.GetAttribute("relight:supersampling").Set(description.supersampling)
    cache.GetAttribute("relight:worldFromCamera").Set(Gf.Matrix4d(description.world_from_camera.T.tolist()))
    cache.GetAttribute("relight:exposureScale").Set(description.exposure_scale)
    cache.GetAttribute("relight:contentHash").Set(description.content_hash)
    files = sorted(description.inputs)
    cache.GetAttribute("relight:inputFiles").Set(Vt.StringArray([os.path.relpath(f, directory) for f in files]))
    cache.GetAttribute("relight:inputHashes").Set(Vt.StringArray([description.inputs[f] for f in files]))
    for name, value in sorted(description.parameters.items()):
        cache.CreateAttribute(f"relight:parameters:{name}", _sdf_type(value), custom=True).Set(value)
    for payload in description.payloads:
        prim = stage.DefinePrim(f"{CACHE_PRIM}/{payload.name}", "RelightPayload")
        prim.GetAttribute("relight:file").Set(Sdf.AssetPath(payload.file))
        prim.GetAttribute("relight:format").Set(payload.format)
        prim.GetAttribute("relight:sha256").Set(payload.sha256)
        prim.GetAttribute("relight:bytes").Set(payload.num_bytes)
        prim.GetAttribute("relight:channels").Set(Vt.StringArray(list(payload.channels)))
        prim.GetAttribute("relight:shape").Set(Vt.Int64Array(list(payload.shape)))
        prim.GetAttribute("relight:dtype").Set(payload.dtype)
        names = sorted(payload.constants)
        prim.GetAttribute("relight:constantChannels").Set(Vt.StringArray(names))
        prim.GetAttribute("relight:constantValues").Set(Vt.DoubleArray([payload.constants[n] for n in names]))
    with atomic_path(path) as temp:
        layer.Export(str(temp))


def _get(prim: Usd.Prim, name: str, path: Path):
    attribute = prim.GetAttribute(name)
    value = attribute.Get() if attribute else None
    if value is None:
        raise RelightError(f"{path}: {prim.GetPath()} has no {name}")
    return value


def read_cache_layer(path: str | os.PathLike) -> CacheDescription:
    """Read a cache layer (payload files are not opened here).

    Raises:
        RelightError: missing file, not a cache layer, unsupported version or missing attributes.
    """
    register_schemas()
    path = Path(path)
    if not path.is_file():
        raise RelightError(f"{path}: no such cache layer")
    try:
        stage = Usd.Stage.Open(str(path), Usd.Stage.LoadNone)
    except Exception as error:  # pxr raises Tf.ErrorException with multi-line text
        raise RelightError(f"{path}: not a readable USD layer ({str(error).splitlines()[0]})") from None
    cache = stage.GetPrimAtPath(CACHE_PRIM)
    if not cache or cache.GetTypeName() != "RelightCache":
        raise RelightError(f"{path}: not a relight cache (no RelightCache prim at {CACHE_PRIM})")
    version = _get(cache, "relight:version", path)
    if version != CACHE_VERSION:
        raise RelightError(f"{path}: cache version {version} is not supported (expected {CACHE_VERSION})")
    directory = path.parent.resolve()
    source = _get(cache, "relight:source", path).path
    files = _get(cache, "relight:inputFiles", path)
    hashes = _get(cache, "relight:inputHashes", path)
    parameters = {a.GetName().split(":", 2)[2]: a.Get() for a in cache.GetAttributes()
                  if a.GetName().startswith("relight:parameters:")}
    payloads = []
    for prim in cache.GetChildren():
        if prim.GetTypeName() != "RelightPayload":
            continue
        names = list(_get(prim, "relight:constantChannels", path))
        values = list(_get(prim, "relight:constantValues", path))
        payloads.append(Payload(
            name=prim.GetName(),
            file=_get(prim, "relight:file", path).path,
            format=_get(prim, "relight:format", path),
            sha256=_get(prim, "relight:sha256", path),
            num_bytes=int(_get(prim, "relight:bytes", path)),
            channels=tuple(_get(prim, "relight:channels", path)),
            shape=tuple(int(n) for n in _get(prim, "relight:shape", path)),
            dtype=_get(prim, "relight:dtype", path),
            constants=dict(zip(names, (float(v) for v in values))),
        ))
    matrix = np.array(_get(cache, "relight:worldFromCamera", path), dtype=np.float64).T
    if not np.all(np.isfinite(matrix)) or math.isclose(abs(np.linalg.det(matrix[:3, :3])), 0.0):
        raise RelightError(f"{path}: relight:worldFromCamera is not a valid transform")
    return CacheDescription(
        method=_get(cache, "relight:method", path),
        source=str((directory / source).resolve()),
        camera_path=_get(cache, "relight:cameraPath", path),
        resolution=tuple(int(v) for v in _get(cache, "relight:resolution", path)),
        supersampling=int(_get(cache, "relight:supersampling", path)),
        world_from_camera=matrix,
        exposure_scale=float(_get(cache, "relight:exposureScale", path)),
        content_hash=_get(cache, "relight:contentHash", path),
        inputs={str((directory / f).resolve()): h for f, h in zip(files, hashes)},
        parameters=parameters,
        payloads=tuple(payloads),
    )
