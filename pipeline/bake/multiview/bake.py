"""`relight bake --method multiview`: caching cameras and their deep framebuffers, as one cache.

Writes into OUT:
    <stem>.relight.usda         the cache layer (method 'multiview'); its camera, resolution and
                                supersampling are the shot camera's: the default view to render
    <stem>.view000.exr ...      one deep framebuffer per caching camera (supersampling 1, each at
                                its own square resolution; channels as `relight_torch.cache.gbuffer_exr`)
    <stem>.cameras.npy          (K, C) float64 camera table (`relight_torch.multiview.views.CAMERA_COLUMNS`)
    <stem>.occluders.npy, .occluderObjects.npy, .objectPaths.npy   as the direct cache's
    <stem>.cornerNormals.npy    (T, 3, 3) float16 shading normals of the occluders' corners
    <stem>.normalMapped.npy     (num_materials,) bool: the material perturbs its normal (a normal
                                map or a constant other than +Z): its cached normals are kept
The coverage statistics are cache parameters: coverage (the threshold), uncoveredFraction,
primaryFraction, numPrimary, numSecondary, numViews, numSamples, numUnreachable, numSpheres.

The placement runs in this process (it is sequential: each camera depends on the coverage of the
ones before); the caching views' deep framebuffers are scheduler chunks (`pipeline.bake.scheduler`),
one per view, computed from the camera's table row, so a killed bake resumes from its finished
views and a cluster bakes them in parallel. Each file is written atomically; the layer last.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from pipeline.bake.deep_framebuffer import bake_deep_framebuffer
from pipeline.bake.direct.bake import prepare_output, write_npy
from pipeline.bake.inputs import code_version, identify_bake
from pipeline.bake.multiview.cameras import camera_from_row, camera_row
from pipeline.bake.multiview.placement import Placement, PlacementSettings, place_cameras
from pipeline.bake.scheduler import (
    ChunkSpec,
    ShotSpec,
    chunk_folder,
    load_chunk,
    load_shot,
    run_chunks,
    shot_tracer,
)
from pipeline.errors import RelightError
from pipeline.scene.types import Camera, Scene
from pipeline.tracing import shared_tracer
from relight_torch.cache.gbuffer_exr import gbuffer_to_channels
from relight_torch.cache.layer import CacheDescription, Payload, file_sha256, read_cache_layer, write_cache_layer
from relight_torch.io.exr import write_exr
from relight_torch.lights.linking import encode_paths
from relight_torch.multiview.load import view_payload_name

CONSTANT_PREFIX = "constant:"
"""Chunk arrays holding a constant (elided) channel's value, as 0-d arrays."""


def _view_chunk(spec: ChunkSpec) -> dict[str, np.ndarray]:
    """The deep framebuffer of caching camera `spec.start` (its table row is the 'camera' parameter),
    as EXR channels plus its constant channels under CONSTANT_PREFIX."""
    scene, _ = load_shot(spec.shot)
    camera = camera_from_row(np.asarray(spec.param("camera"), np.float64), f"/Caching/view{spec.start}")
    dfb = bake_deep_framebuffer(scene, camera, 1, spec.param("textureSamples"), tracer=shot_tracer(spec.shot))
    channels, constants = gbuffer_to_channels(dfb.gbuffer)
    return channels | {CONSTANT_PREFIX + name: np.array(value) for name, value in constants.items()}


def coverage_parameters(placement: Placement, settings: PlacementSettings) -> dict:
    """The placement's statistics and settings as cache parameters."""
    return {
        "coverage": float(settings.coverage),
        "uncoveredFraction": placement.uncovered_fraction,
        "primaryFraction": placement.primary_fraction,
        "numPrimary": placement.num_primary,
        "numSecondary": placement.num_secondary,
        "numViews": len(placement.cameras),
        "numSamples": placement.num_samples,
        "numUnreachable": placement.num_unreachable,
        "numSpheres": placement.num_spheres,
        "maxResolution": settings.max_resolution,
        "seed": settings.seed,
        "box": " ".join(f"{v:.9g}" for v in np.concatenate(placement.box)),
    }


def normal_mapped(scene: Scene) -> np.ndarray:
    """(num_materials,) bool: the material's normal input is a texture or a constant other than +Z."""
    return np.array(
        [m.normal.texture is not None or not np.allclose(m.normal.value, (0.0, 0.0, 1.0)) for m in scene.materials],
        bool,
    ).reshape(-1)


def coverage_summary(layer_path: Path) -> str:
    """One line of a multiview cache's coverage statistics, for the bake's report."""
    description = read_cache_layer(layer_path)
    p = description.parameters
    views = sum(payload.num_bytes for payload in description.payloads if payload.name.startswith("view"))
    return (
        f"{p['numViews']} caching views ({p['numPrimary']} omni-directional cameras, {p['numSecondary']} "
        f"secondary) cover {100 * (1 - p['uncoveredFraction']):.1f}% of the surfaces' importance "
        f"(threshold {100 * (1 - p['coverage']):.1f}%; primary {100 * p['primaryFraction']:.1f}%; "
        f"{p['numUnreachable']} of {p['numSamples']} samples unreachable); deep framebuffers {views / 1e6:.1f} MB"
    )


def bake_multiview(
    scene: Scene,
    camera: Camera,
    out_dir: str | Path,
    stem: str,
    supersampling: int = 1,
    texture_samples: int = 2,
    time_code: float | None = None,
    settings: PlacementSettings = PlacementSettings(),
    box: tuple[np.ndarray, np.ndarray] | None = None,
) -> Path:
    """Place caching cameras, bake a deep framebuffer for each, write the cache; returns the layer's path.

    Args:
        camera: the shot camera: the default view of `relight render` (and its supersampling).
        supersampling: sub-samples per pixel side of the rendered views (caching views use 1).
        texture_samples: material samples per caching-view pixel side (texture filtering).
        settings: the placement's parameters.
        box: (lo, hi) workspace; default the scene's bounds.
    """
    out_dir, layer_path = prepare_output(out_dir, stem, supersampling, texture_samples)
    placement = place_cameras(scene, settings, box, shared_tracer(scene))
    if not placement.cameras:
        raise RelightError(f"{scene.source}: no caching camera sees the surfaces inside the box")
    rows = [camera_row(placed.camera, placed.kind, placed.group) for placed in placement.cameras]
    parameters, inputs, digest = identify_bake(
        scene, {"textureSamples": texture_samples} | coverage_parameters(placement, settings), time_code
    )
    chunk_dir = chunk_folder(out_dir, stem, "multiview", digest)
    shot = ShotSpec.of(scene, camera, time_code)
    specs = [
        ChunkSpec(shot, "view", (("camera", tuple(row.tolist())), ("textureSamples", texture_samples)), k, k + 1)
        for k, row in enumerate(rows)
    ]
    payloads = []
    for k, chunk in enumerate(run_chunks(_view_chunk, specs, chunk_dir, "caching views", "views")):
        arrays = load_chunk(chunk)
        constants = {
            name[len(CONSTANT_PREFIX) :]: float(value)
            for name, value in arrays.items()
            if name.startswith(CONSTANT_PREFIX)
        }
        channels = {name: value for name, value in arrays.items() if not name.startswith(CONSTANT_PREFIX)}
        path = out_dir / f"{stem}.{view_payload_name(k)}.exr"
        write_exr(path, channels, {"relight:supersampling": 1})
        payloads.append(
            Payload(
                name=view_payload_name(k),
                file=path.name,
                format="exr",
                sha256=file_sha256(path),
                num_bytes=path.stat().st_size,
                channels=tuple(sorted(channels)),
                shape=next(iter(channels.values())).shape[:2],
                constants=constants,
            )
        )
    payloads += [
        write_npy(out_dir / f"{stem}.cameras.npy", np.array(rows, np.float64).reshape(len(rows), -1), "cameras"),
        write_npy(out_dir / f"{stem}.occluders.npy", scene.geometry.positions.astype(np.float32), "occluders"),
        write_npy(
            out_dir / f"{stem}.occluderObjects.npy", scene.geometry.object_ids.astype(np.int32), "occluderObjects"
        ),
        write_npy(
            out_dir / f"{stem}.objectPaths.npy", encode_paths([obj.path for obj in scene.objects]), "objectPaths"
        ),
        write_npy(out_dir / f"{stem}.cornerNormals.npy", scene.geometry.normals.astype(np.float16), "cornerNormals"),
        write_npy(out_dir / f"{stem}.normalMapped.npy", normal_mapped(scene), "normalMapped"),
    ]
    description = CacheDescription(
        method="multiview",
        source=scene.source,
        camera_path=camera.path,
        resolution=(camera.width, camera.height),
        supersampling=supersampling,
        world_from_camera=camera.world_from_camera,
        exposure_scale=camera.exposure_scale,
        content_hash=digest,
        inputs=inputs,
        parameters=parameters,
        payloads=tuple(payloads),
        code_version=code_version(),
    )
    write_cache_layer(layer_path, description)
    shutil.rmtree(chunk_dir, ignore_errors=True)
    return layer_path
