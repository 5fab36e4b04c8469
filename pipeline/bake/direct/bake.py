"""`relight bake --method direct`: the deep framebuffer and the occluders, as a cache.

Writes into OUT:
    <stem>.relight.usda     the cache layer (RelightCache prim, provenance, payload list)
    <stem>.dfb.exr          the deep framebuffer (channels in relight_torch.cache.gbuffer_exr)
    <stem>.occluders.npy    (T, 3, 3) float32 world triangles: shadows without the shot
    <stem>.occluderObjects.npy  (T,) int32 object id of each occluder triangle
    <stem>.objectPaths.npy  uint8 UTF-8 object prim paths by object id, newline-separated: light
                            and shadow links are resolved against them at relight time
    <stem>.materialPaths.npy  the same of the material prim paths by material id ('<fallback>',
                            '<displayColor>' for unbound gprims): materials are edited by path
    <stem>.opacity*.npy     only when some occluder is cut out or partially opaque: its opacity
                            table (`relight_torch.visibility.opacity.OpacityTable.to_arrays`), so
                            that shadow rays and shadow maps pass through the holes
The deep framebuffer is traced in bands of `rows_per_chunk` pixel rows, chunks of
`pipeline.bake.scheduler` kept in `.<stem>.direct-<hash>/` until the layer is written, so a killed
bake resumes from its finished bands. Each file is written atomically; the layer last, so a cache
layer never names a missing payload.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np

from pipeline.bake.deep_framebuffer import bake_deep_framebuffer
from pipeline.bake.inputs import code_version, identify_bake
from pipeline.bake.scheduler import (
    ChunkSpec,
    ShotSpec,
    chunk_folder,
    chunk_ranges,
    load_chunk,
    load_shot,
    run_chunks,
    shot_tracer,
)
from pipeline.errors import warn
from pipeline.scene.opacity import scene_opacity
from pipeline.scene.types import Camera, Scene
from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.cache.gbuffer_exr import gbuffer_to_channels
from relight_torch.cache.layer import SUFFIX, CacheDescription, Payload, file_sha256, write_cache_layer
from relight_torch.gbuffer import GBuffer
from relight_torch.io.atomic import atomic_path, remove_temp_files
from relight_torch.io.exr import write_exr
from relight_torch.lights.linking import encode_paths

SUBSAMPLES_PER_CHUNK = 1 << 17
"""Sub-samples per deep-framebuffer chunk (whole pixel rows, at least one): a chunk's memory follows
this, not the image width (with supersampling 2 and 2 x 2 texture samples, 524,288 probe rays)."""


def rows_per_chunk(width: int, supersampling: int) -> int:
    """Pixel rows per chunk of an image `width` pixels wide: `SUBSAMPLES_PER_CHUNK` sub-samples."""
    return max(1, SUBSAMPLES_PER_CHUNK // (width * supersampling * supersampling))


_PARAM_PREFIX = "param_"
_BACK_FACING = "numBackFacing"
BACK_FACING_WARNING = 0.5
"""Warn when more than this share of the covered sub-samples see back faces of single-sided surfaces."""


def write_npy(path: Path, array: np.ndarray, name: str = "") -> Payload:
    """Write a .npy payload atomically and describe it (as payload `name`)."""
    with atomic_path(path) as temp, open(temp, "wb") as handle:
        np.save(handle, array, allow_pickle=False)
    return Payload(
        name=name,
        file=path.name,
        format="npy",
        sha256=file_sha256(path),
        num_bytes=path.stat().st_size,
        shape=tuple(array.shape),
        dtype=array.dtype.name,
    )


def _direct_chunk(spec: ChunkSpec) -> dict[str, np.ndarray]:
    """The deep framebuffer of pixel rows [start, stop): the GBuffer's per-sample arrays, material
    parameters prefixed with _PARAM_PREFIX."""
    scene, camera = load_shot(spec.shot)
    dfb = bake_deep_framebuffer(
        scene,
        camera,
        spec.param("supersampling"),
        spec.param("textureSamples"),
        tracer=shot_tracer(spec.shot),
        rows=(spec.start, spec.stop),
    )
    arrays = {
        f.name: getattr(dfb.gbuffer, f.name).numpy()
        for f in dataclasses.fields(GBuffer)
        if f.name not in ("image_size", "params", "camera_position")
    }
    arrays.update(
        {
            _PARAM_PREFIX + f.name: getattr(dfb.gbuffer.params, f.name).numpy()
            for f in dataclasses.fields(PreviewSurfaceParams)
        }
    )
    arrays[_BACK_FACING] = np.array(dfb.num_back_facing)
    return arrays


def _join_bands(
    chunks: list[dict[str, np.ndarray]], image_size: tuple[int, int], camera_position: np.ndarray
) -> GBuffer:
    """The bands' arrays (`_direct_chunk`, in row order) as one GBuffer of the whole image."""
    joined = {name: np.concatenate([c[name] for c in chunks]) for name in chunks[0] if name != _BACK_FACING}
    params = PreviewSurfaceParams.from_numpy(
        {name[len(_PARAM_PREFIX) :]: joined.pop(name) for name in list(joined) if name.startswith(_PARAM_PREFIX)}
    )
    return GBuffer.from_numpy(image_size=image_size, params=params, camera_position=camera_position, **joined)


def direct_payloads(
    scene: Scene,
    camera: Camera,
    out_dir: Path,
    stem: str,
    supersampling: int,
    texture_samples: int,
    time_code: float | None,
) -> tuple[CacheDescription, Path]:
    """Write the direct payloads; the cache's description (not yet written) and the chunk folder
    to remove once its layer is written."""
    parameters, inputs, digest = identify_bake(
        scene, {"supersampling": supersampling, "textureSamples": texture_samples}, time_code
    )
    chunk_dir = chunk_folder(out_dir, stem, "direct", digest)
    shot = ShotSpec.of(scene, camera, time_code)
    specs = [
        ChunkSpec(
            shot,
            "deepFramebuffer",
            (("supersampling", supersampling), ("textureSamples", texture_samples)),
            first,
            last,
        )
        for first, last in chunk_ranges(camera.height, rows_per_chunk(camera.width, supersampling))
    ]
    paths = run_chunks(_direct_chunk, specs, chunk_dir, "deep framebuffer", "rows")
    camera_position = camera.world_from_camera[:3, 3]
    chunks = [load_chunk(path) for path in paths]
    gbuffer = _join_bands(chunks, (camera.height * supersampling, camera.width * supersampling), camera_position)
    back_facing = sum(int(c[_BACK_FACING]) for c in chunks)
    if back_facing > BACK_FACING_WARNING * gbuffer.num_samples:
        warn(
            f"{scene.source}: camera {camera.path} sees the back of single-sided surfaces in "
            f"{back_facing / gbuffer.num_samples:.0%} of its covered samples: is it inside geometry?",
            scene.warnings,
        )
    channels, constants = gbuffer_to_channels(gbuffer)
    dfb_path = out_dir / f"{stem}.dfb.exr"
    write_exr(dfb_path, channels, {"relight:supersampling": supersampling})
    deep = Payload(
        name="deepFramebuffer",
        file=dfb_path.name,
        format="exr",
        sha256=file_sha256(dfb_path),
        num_bytes=dfb_path.stat().st_size,
        channels=tuple(sorted(channels)),
        constants=constants,
    )
    # The soup is float32 / int32 already: written without a copy.
    occluders = write_npy(
        out_dir / f"{stem}.occluders.npy", np.ascontiguousarray(scene.geometry.positions, np.float32), "occluders"
    )
    occluder_objects = write_npy(
        out_dir / f"{stem}.occluderObjects.npy",
        np.ascontiguousarray(scene.geometry.object_ids, np.int32),
        "occluderObjects",
    )
    object_paths = write_npy(
        out_dir / f"{stem}.objectPaths.npy", encode_paths([obj.path for obj in scene.objects]), "objectPaths"
    )
    material_paths = write_npy(
        out_dir / f"{stem}.materialPaths.npy", encode_paths([m.path for m in scene.materials]), "materialPaths"
    )
    opacity = scene_opacity(scene)
    opacity_payloads = (
        ()
        if opacity is None
        else tuple(
            write_npy(out_dir / f"{stem}.{name}.npy", array, name) for name, array in opacity.to_arrays().items()
        )
    )
    description = CacheDescription(
        method="direct",
        source=scene.source,
        camera_path=camera.path,
        resolution=(camera.width, camera.height),
        supersampling=supersampling,
        world_from_camera=camera.world_from_camera,
        exposure_scale=camera.exposure_scale,
        content_hash=digest,
        inputs=inputs,
        parameters=parameters,
        payloads=(deep, occluders, occluder_objects, object_paths, material_paths) + opacity_payloads,
        code_version=code_version(),
    )
    return description, chunk_dir


def prepare_output(out_dir: str | Path, stem: str, supersampling: int, texture_samples: int) -> tuple[Path, Path]:
    """Check the sampling rates, create `out_dir`, remove the old layer and killed writers' temp
    files of `stem`; (out_dir, the layer's path)."""
    if supersampling < 1 or texture_samples < 1:
        raise ValueError(f"supersampling and texture_samples must be >= 1, got {supersampling}, {texture_samples}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    layer_path = out_dir / f"{stem}{SUFFIX}"
    # An old layer must not survive beside new payloads if this bake dies midway.
    layer_path.unlink(missing_ok=True)
    remove_temp_files(out_dir, f"{stem}.")
    return out_dir, layer_path


def bake_direct(
    scene: Scene,
    camera: Camera,
    out_dir: str | Path,
    stem: str,
    supersampling: int = 2,
    texture_samples: int = 4,
    time_code: float | None = None,
) -> Path:
    """Bake the direct-lighting cache of `camera`; returns the cache layer's path.

    Args:
        supersampling: sub-samples per pixel side (box-filtered after shading).
        texture_samples: material samples per sub-sample side (texture filtering).
        time_code: the time the scene was read at (recorded so lights are read at the same time).
    """
    out_dir, layer_path = prepare_output(out_dir, stem, supersampling, texture_samples)
    description, chunk_dir = direct_payloads(scene, camera, out_dir, stem, supersampling, texture_samples, time_code)
    write_cache_layer(layer_path, description)
    shutil.rmtree(chunk_dir, ignore_errors=True)
    return layer_path
