"""`relight bake --method direct`: the deep framebuffer and the occluders, as a cache.

Writes into OUT:
    <stem>.relight.usda     the cache layer (RelightCache prim, provenance, payload list)
    <stem>.dfb.exr          the deep framebuffer (channels in relight_torch.cache.gbuffer_exr)
    <stem>.occluders.npy    (T, 3, 3) float32 world triangles: shadows without the shot
    <stem>.occluderObjects.npy  (T,) int32 object id of each occluder triangle
    <stem>.objectPaths.npy  uint8 UTF-8 object prim paths by object id, newline-separated: light
                            and shadow links are resolved against them at relight time
Each file is written atomically; the layer last, so a cache layer never names a missing payload.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline import __version__
from pipeline.bake.deep_framebuffer import bake_deep_framebuffer
from pipeline.bake.inputs import hash_inputs, input_files
from pipeline.scene.types import Camera, Scene
from relight_torch.cache.gbuffer_exr import gbuffer_to_channels
from relight_torch.cache.layer import (SUFFIX, CacheDescription, Payload, content_hash, file_sha256,
                                       write_cache_layer)
from relight_torch.io.atomic import atomic_path
from relight_torch.io.exr import write_exr
from relight_torch.lights.linking import encode_paths


def write_npy(path: Path, array: np.ndarray, name: str = "") -> Payload:
    """Write a .npy payload atomically and describe it (as payload `name`)."""
    with atomic_path(path) as temp:
        with open(temp, "wb") as handle:
            np.save(handle, array, allow_pickle=False)
    return Payload(name=name, file=path.name, format="npy", sha256=file_sha256(path),
                   num_bytes=path.stat().st_size, shape=tuple(array.shape), dtype=array.dtype.name)


def bake_direct(scene: Scene, camera: Camera, out_dir: str | Path, stem: str, supersampling: int = 2,
                texture_samples: int = 2, time_code: float | None = None) -> Path:
    """Bake the direct-lighting cache of `camera`; returns the cache layer's path.

    Args:
        supersampling: sub-samples per pixel side (box-filtered after shading).
        texture_samples: material samples per sub-sample side (texture filtering).
        time_code: the time the scene was read at (recorded so lights are read at the same time).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    layer_path = out_dir / f"{stem}{SUFFIX}"
    # An old layer must not survive beside new payloads if this bake dies midway.
    layer_path.unlink(missing_ok=True)
    dfb = bake_deep_framebuffer(scene, camera, supersampling, texture_samples)
    channels, constants = gbuffer_to_channels(dfb.gbuffer)
    dfb_path = out_dir / f"{stem}.dfb.exr"
    write_exr(dfb_path, channels, {"relight:supersampling": supersampling})
    deep = Payload(name="deepFramebuffer", file=dfb_path.name, format="exr", sha256=file_sha256(dfb_path),
                   num_bytes=dfb_path.stat().st_size, channels=tuple(sorted(channels)), constants=constants)
    occluders = write_npy(out_dir / f"{stem}.occluders.npy", scene.geometry.positions.astype(np.float32))
    occluders = Payload(**{**vars(occluders), "name": "occluders"})
    occluder_objects = write_npy(out_dir / f"{stem}.occluderObjects.npy",
                                 scene.geometry.object_ids.astype(np.int32), "occluderObjects")
    object_paths = write_npy(out_dir / f"{stem}.objectPaths.npy",
                             encode_paths([obj.path for obj in scene.objects]), "objectPaths")
    parameters: dict = {"supersampling": supersampling, "textureSamples": texture_samples}
    if time_code is not None:
        parameters["time"] = float(time_code)
    inputs = hash_inputs(input_files(scene))
    description = CacheDescription(
        method="direct", source=scene.source, camera_path=camera.path,
        resolution=(camera.width, camera.height), supersampling=supersampling,
        world_from_camera=camera.world_from_camera, exposure_scale=camera.exposure_scale,
        content_hash=content_hash(inputs, parameters, __version__), inputs=inputs,
        parameters=parameters, payloads=(deep, occluders, occluder_objects, object_paths),
    )
    write_cache_layer(layer_path, description)
    return layer_path
