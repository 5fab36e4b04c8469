"""The cache layer: `<stem>.relight.usda`, authored with our codeless schema (`relight_torch/schemas/`).

    def RelightCache "Cache"            method, version, source stage, camera, resolution,
        matrix4d relight:worldFromCamera    supersampling, content hash, the inputs and their hashes,
        relight:parameters:<name> = ...     the method's parameters (one typed attribute each)
        def RelightPayload "<name>"     one per payload file: relative path, format, sha256, bytes,
                                            EXR channels or .npy shape and dtype, and the channels
                                            elided because constant (name + value)

Payload files sit beside the layer and are referenced by relative asset paths. Nothing here is
pickled; writes are atomic (temp file, then rename). The layer carries the shot's upAxis and
metersPerUnit (positions and transforms in it are in the shot's units) and a defaultPrim, so it is
clean under UsdValidation's validators (see `relight_torch.cache.validation` for ours).

Reading trusts nothing: every attribute must be authored with its schema type (a schema fallback
does not stand in for a value the writer always authors), arrays that go together must have the
same length, and numbers must be in range; each problem is one `RelightError` line naming the
layer, prim and attribute.
"""

from __future__ import annotations

import hashlib
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

from relight_torch.errors import RelightError
from relight_torch.io.atomic import atomic_path
from relight_torch.methods import METHOD_NAMES
from relight_torch.schema import register_schemas
from relight_torch.stage import usd_error_line

CACHE_PRIM = "/Cache"
CACHE_VERSION = 2
"""Cache format version: 2 added object ids to the indirect methods' gathers (light linking) and the
gather method's shared surface points; caches of another version are refused with 're-bake it'."""
SUFFIX = ".relight.usda"
FORMATS = ("exr", "npy")
_SHA256 = re.compile(r"[0-9a-f]{64}")


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
        shape, dtype: array shape and numpy dtype name (npy); for exr, shape is empty (the image is
            the cache's resolution times its supersampling) or the image's (H, W) where it differs.
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
        code_version: the code that baked it (package version + digest of its sources); ''
            when not recorded.
        layer: the cache layer it was read from ('' for one not read from a file), for messages.
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
    code_version: str = ""
    layer: str = ""

    def payload(self, name: str) -> Payload:
        for payload in self.payloads:
            if payload.name == name:
                return payload
        raise RelightError(
            f"{self.layer or 'cache'}: has no payload named {name!r} (has {[p.name for p in self.payloads]})"
        )


def file_sha256(path: str | os.PathLike[str]) -> str:
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


def _sdf_type(value: object) -> Sdf.ValueTypeName:
    if isinstance(value, bool):
        return Sdf.ValueTypeNames.Bool
    if isinstance(value, int):
        return Sdf.ValueTypeNames.Int64
    if isinstance(value, float):
        return Sdf.ValueTypeNames.Double
    if isinstance(value, str):
        return Sdf.ValueTypeNames.String
    raise TypeError(f"cache parameter of unsupported type {type(value).__name__}: {value!r}")


def _anchored(relative: str) -> str:
    """A layer-relative asset path spelled `./x` or `../x`: USD treats a bare `x` as a search path."""
    if os.path.isabs(relative) or relative.startswith(("./", "../")):
        return relative
    return f"./{relative}"


def shot_units(source: str | os.PathLike[str]) -> tuple[str, float]:
    """(upAxis, metersPerUnit) of a shot, from its root layer's metadata (USD's fallbacks if unset).

    Raises:
        RelightError: the shot's root layer cannot be opened.
    """
    try:
        layer = Sdf.Layer.FindOrOpen(os.fspath(source))
    except Exception as error:  # pxr raises Tf.ErrorException with multi-line text
        raise RelightError(f"{source}: not a readable USD layer ({usd_error_line(error)})") from None
    if layer is None:
        raise RelightError(f"{source}: no such USD layer (the cache's source)")
    root = layer.pseudoRoot
    up_axis = root.GetInfo("upAxis") if root.HasInfo("upAxis") else UsdGeom.GetFallbackUpAxis()
    meters_per_unit = (
        root.GetInfo("metersPerUnit") if root.HasInfo("metersPerUnit") else UsdGeom.LinearUnits.centimeters
    )
    return str(up_axis), float(meters_per_unit)


def write_cache_layer(path: str | os.PathLike[str], description: CacheDescription) -> None:
    """Author the cache layer atomically. Payload files must already be written beside it.

    Raises:
        RelightError: the description's source (the shot) cannot be opened for its units.
    """
    register_schemas()
    path = Path(path)
    directory = path.parent.resolve()
    layer = Sdf.Layer.CreateAnonymous(SUFFIX)
    stage = Usd.Stage.Open(layer)
    up_axis, meters_per_unit = shot_units(description.source)
    UsdGeom.SetStageUpAxis(stage, up_axis)
    UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    layer.documentation = (
        f"relight {description.method} cache of {description.camera_path} in "
        f"{os.path.relpath(description.source, directory)}"
    )
    cache = stage.DefinePrim(CACHE_PRIM, "RelightCache")
    stage.SetDefaultPrim(cache)
    cache.GetAttribute("relight:method").Set(description.method)
    cache.GetAttribute("relight:version").Set(CACHE_VERSION)
    cache.GetAttribute("relight:source").Set(Sdf.AssetPath(_anchored(os.path.relpath(description.source, directory))))
    cache.GetAttribute("relight:cameraPath").Set(description.camera_path)
    cache.GetAttribute("relight:resolution").Set(Gf.Vec2i(*description.resolution))
    cache.GetAttribute("relight:supersampling").Set(description.supersampling)
    cache.GetAttribute("relight:worldFromCamera").Set(Gf.Matrix4d(description.world_from_camera.T.tolist()))
    cache.GetAttribute("relight:exposureScale").Set(description.exposure_scale)
    cache.GetAttribute("relight:contentHash").Set(description.content_hash)
    cache.GetAttribute("relight:codeVersion").Set(description.code_version)
    files = sorted(description.inputs)
    cache.GetAttribute("relight:inputFiles").Set(Vt.StringArray([os.path.relpath(f, directory) for f in files]))
    cache.GetAttribute("relight:inputHashes").Set(Vt.StringArray([description.inputs[f] for f in files]))
    for name, value in sorted(description.parameters.items()):
        cache.CreateAttribute(f"relight:parameters:{name}", _sdf_type(value), custom=True).Set(value)
    for payload in description.payloads:
        prim = stage.DefinePrim(f"{CACHE_PRIM}/{payload.name}", "RelightPayload")
        prim.GetAttribute("relight:file").Set(Sdf.AssetPath(_anchored(payload.file)))
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
        if not layer.Export(str(temp)):
            raise OSError(f"{path}: could not write the cache layer")


def is_cache_layer(path: str | os.PathLike[str]) -> bool:
    """True when `path` is a USD layer defining a RelightCache prim at CACHE_PRIM (by content, not name)."""
    try:
        layer = Sdf.Layer.FindOrOpen(os.fspath(path))
    except Exception:  # pxr raises Tf.ErrorException for unreadable files: not a cache layer
        return False
    spec = layer.GetPrimAtPath(CACHE_PRIM) if layer is not None else None
    return spec is not None and spec.typeName == "RelightCache"


def _get(prim: Usd.Prim, name: str, path: Path) -> Any:
    """The authored value of `name`, checked against its schema type (its Python type varies with it)."""
    attribute = prim.GetAttribute(name)
    if not attribute or not attribute.HasAuthoredValue():
        raise RelightError(f"{path}: {prim.GetPath()}.{name} is missing (the layer was edited; re-bake)")
    value = attribute.Get()
    expected = type(attribute.GetTypeName().defaultValue)
    if not isinstance(value, expected) or (expected is int and isinstance(value, bool)):
        raise RelightError(f"{path}: {prim.GetPath()}.{name} = {value!r} is not a {attribute.GetTypeName()}")
    return value


def _require(condition: bool, path: Path, prim: Usd.Prim, message: str) -> None:
    if not condition:
        raise RelightError(f"{path}: {prim.GetPath()}.{message}")


def plain_dtype(name: str) -> bool:
    """True for the name of a numpy dtype holding no Python objects (nothing that needs pickle)."""
    try:
        return bool(name) and not np.dtype(name).hasobject
    except (TypeError, ValueError, SyntaxError):
        return False


def _read_payload(prim: Usd.Prim, path: Path) -> Payload:
    """One RelightPayload prim, its attributes checked for consistency."""
    names = list(_get(prim, "relight:constantChannels", path))
    values = [float(v) for v in _get(prim, "relight:constantValues", path)]
    _require(
        len(names) == len(values),
        path,
        prim,
        f"relight:constantValues has {len(values)} values for {len(names)} relight:constantChannels",
    )
    file = _get(prim, "relight:file", path).path
    _require(bool(file), path, prim, "relight:file is empty")
    # Payloads live beside their layer: a path out of its folder would let an edited layer make
    # the relighter read (and report on) any file.
    normal = os.path.normpath(file)
    outside = os.path.isabs(file) or normal in (os.curdir, os.pardir) or normal.startswith(os.pardir + os.sep)
    _require(not outside, path, prim, f"relight:file {file!r} is not a file in the cache layer's own folder")
    payload = Payload(
        name=prim.GetName(),
        file=normal,
        format=_get(prim, "relight:format", path),
        sha256=_get(prim, "relight:sha256", path),
        num_bytes=int(_get(prim, "relight:bytes", path)),
        channels=tuple(_get(prim, "relight:channels", path)),
        shape=tuple(int(n) for n in _get(prim, "relight:shape", path)),
        dtype=_get(prim, "relight:dtype", path),
        constants=dict(zip(names, values, strict=True)),
    )
    _require(payload.format in FORMATS, path, prim, f"relight:format {payload.format!r} is not one of {FORMATS}")
    _require(
        _SHA256.fullmatch(payload.sha256) is not None,
        path,
        prim,
        f"relight:sha256 {payload.sha256!r} is not a sha256 hex digest",
    )
    _require(payload.num_bytes > 0, path, prim, f"relight:bytes = {payload.num_bytes} must be > 0")
    if payload.format == "exr":
        _require(len(payload.channels) > 0, path, prim, "relight:channels is empty for an EXR payload")
        _require(
            payload.shape == () or (len(payload.shape) == 2 and min(payload.shape) > 0),
            path,
            prim,
            f"relight:shape {list(payload.shape)} of an EXR payload must be empty or a positive (H, W)",
        )
    else:
        _require(all(n >= 0 for n in payload.shape), path, prim, f"relight:shape {list(payload.shape)} is negative")
        _require(
            plain_dtype(payload.dtype),
            path,
            prim,
            f"relight:dtype {payload.dtype!r} is not a numpy dtype without objects",
        )
    return payload


def read_cache_layer(path: str | os.PathLike[str]) -> CacheDescription:
    """Read a cache layer (payload files are not opened here).

    Raises:
        RelightError: missing file, not a cache layer, unsupported version, or an attribute that is
            missing, of the wrong type or inconsistent with the others (one line naming it).
    """
    register_schemas()
    path = Path(path)
    if not path.is_file():
        raise RelightError(f"{path}: no such cache layer")
    try:
        stage = Usd.Stage.Open(str(path), Usd.Stage.LoadNone)
    except Exception as error:  # pxr raises Tf.ErrorException with multi-line text
        raise RelightError(f"{path}: not a readable USD layer ({usd_error_line(error)})") from None
    cache = stage.GetPrimAtPath(CACHE_PRIM)
    if not cache or cache.GetTypeName() != "RelightCache":
        raise RelightError(f"{path}: not a relight cache (no RelightCache prim at {CACHE_PRIM})")
    version = _get(cache, "relight:version", path)
    if version != CACHE_VERSION:
        raise RelightError(
            f"{path}: cache version {version} is not supported (this relight reads version {CACHE_VERSION}); re-bake it"
        )
    method = _get(cache, "relight:method", path)
    _require(method in METHOD_NAMES, path, cache, f"relight:method {method!r} is not one of {METHOD_NAMES}")
    directory = path.parent.resolve()
    source = _get(cache, "relight:source", path).path
    _require(bool(source), path, cache, "relight:source is empty")
    files = list(_get(cache, "relight:inputFiles", path))
    hashes = list(_get(cache, "relight:inputHashes", path))
    _require(
        len(files) == len(hashes),
        path,
        cache,
        f"relight:inputHashes has {len(hashes)} entries for {len(files)} relight:inputFiles",
    )
    camera_path = _get(cache, "relight:cameraPath", path)
    _require(
        Sdf.Path.IsValidPathString(camera_path)
        and Sdf.Path(camera_path).IsAbsolutePath()
        and Sdf.Path(camera_path).IsPrimPath(),
        path,
        cache,
        f"relight:cameraPath {camera_path!r} is not an absolute prim path",
    )
    width, height = _get(cache, "relight:resolution", path)  # an int2 (Gf.Vec2i), checked by _get
    resolution = (int(width), int(height))
    _require(min(resolution) > 0, path, cache, f"relight:resolution {list(resolution)} must be positive")
    supersampling = int(_get(cache, "relight:supersampling", path))
    _require(supersampling >= 1, path, cache, f"relight:supersampling = {supersampling} must be >= 1")
    exposure_scale = float(_get(cache, "relight:exposureScale", path))
    _require(
        math.isfinite(exposure_scale) and exposure_scale >= 0,
        path,
        cache,
        f"relight:exposureScale = {exposure_scale} must be finite and >= 0",
    )
    matrix = np.array(_get(cache, "relight:worldFromCamera", path), dtype=np.float64).T
    _require(
        bool(np.all(np.isfinite(matrix))) and not math.isclose(abs(np.linalg.det(matrix[:3, :3])), 0.0),
        path,
        cache,
        "relight:worldFromCamera is not a valid transform",
    )
    parameters = {
        a.GetName().split(":", 2)[2]: a.Get()
        for a in cache.GetAttributes()
        if a.GetName().startswith("relight:parameters:")
    }
    payloads = tuple(
        _read_payload(prim, path) for prim in cache.GetChildren() if prim.GetTypeName() == "RelightPayload"
    )
    return CacheDescription(
        method=method,
        source=str((directory / source).resolve()),
        camera_path=camera_path,
        resolution=resolution,
        supersampling=supersampling,
        world_from_camera=matrix,
        exposure_scale=exposure_scale,
        content_hash=_get(cache, "relight:contentHash", path),
        inputs={str((directory / f).resolve()): h for f, h in zip(files, hashes, strict=True)},
        parameters=parameters,
        payloads=payloads,
        code_version=str(cache.GetAttribute("relight:codeVersion").Get() or ""),
        layer=str(path),
    )
