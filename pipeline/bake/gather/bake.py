"""`relight bake --method gather`: the direct cache plus clustered gathers (the clustered-gather paper, eq. 2-3).

Writes into OUT, beside the direct method's payloads (`pipeline.bake.direct.bake`):
    <stem>.viewPixels.npy             (P,) int64 pixel (row * W + col) of each view sample (one
                                      per covered pixel centre; the direct part keeps the cache's
                                      supersampling)
    <stem>.viewAlbedo.npy             (P, 3) float32 diffuse albedo of each view sample
    <stem>.gather<Field>.npy          (U, 3) Position (float32), Normal, Albedo (float16) of the
                                      surface points the clustered gathers of both sets share
                                      (`pipeline.bake.gather.surface_points`)
    <stem>.gatherObject.npy           (U,) int32 their object ids (into objectPaths, for light links)
and for each representative set S in ('diffuse', 'glossy') baked:
    <stem>.<S>Index.npy               (G,) int32 shared point of each clustered gather,
                                      representative-major (CSR columns, ascending per row)
    <stem>.<S>Weight.npy              (G, 3) float32 their summed gather weights (CSR values)
    <stem>.<S>Offsets.npy             (R + 1,) int64 CSR offsets of the representatives
    <stem>.<S>Neighbours.npy          (P, k) int32 each view sample's nearest representatives
    <stem>.<S>Rbf.npy                 (P, k) float32 their radial-basis weights
Representatives are gathered in chunks saved under `.<stem>.gather-<hash>/` as they finish; a
killed bake re-run with the same inputs and settings skips the finished chunks. The cache layer
is rewritten last (method 'gather'), then the chunk directory is removed.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pipeline.bake.gather.hemisphere import ClusteredGathers, cluster_gathers, gather
from pipeline.bake.gather.representatives import choose_representatives, glossy_share, reconstruction_weights
from pipeline.bake.gather.surface_points import merge_entries, share_points
from pipeline.bake.indirect import IndirectBake, start_indirect_bake, view_samples
from pipeline.bake.scheduler import (
    ChunkSpec,
    ShotSpec,
    chunk_ranges,
    chunk_threads,
    load_chunk,
    load_shot,
    per_process,
    run_chunks,
    shot_tracer,
)
from pipeline.scene.surface import triangle_tangents
from pipeline.scene.types import Camera, Scene
from pipeline.tracing import Tracer
from relight_torch.brdf.preview_surface import diffuse_albedo
from relight_torch.cache.layer import Payload
from relight_torch.gbuffer import GBuffer
from relight_torch.math.sampling import sobol
from relight_torch.parallel import torch_threads

REFERENCE_PIXELS = 400 * 400
_FIELD_DTYPES = {
    "position": np.float32,
    "normal": np.float16,
    "albedo": np.float16,
    "weight": np.float32,
    "object": np.int32,
}
"""Stored precision: positions and weights in full, unit normals and albedos in half (as the paper
packs its samples in 16-bit floats; their rounding is ~1e-3 relative)."""


@dataclass(frozen=True)
class GatherSettings:
    """What the gather bake keeps.

    Attributes:
        num_directions: QMC hemisphere directions per representative (the paper: 2000).
        num_clusters: clustered gathers per representative (the paper: 120).
        num_representatives: view representatives of both sets together; None scales the
            paper's 40,000 at 400 x 400 with the pixel count.
        num_neighbours: representatives each pixel is reconstructed from (the paper: 10).
        tile: side in pixels of the tiles the view samples are clustered in.
        seed: seed of the QMC scrambling and the per-representative rotations.
        representatives_per_batch: representatives gathered and clustered together (bounds the
            (batch, directions, clusters) distances).
        representatives_per_chunk: representatives per resumable chunk file.
        num_threads: batches gathered concurrently (Embree and torch release the GIL); None: the
            CPUs this process may use.
        point_cells: cells across the scene diagonal of the grid the clustered gathers share
            surface points on (`surface_points.share_points`); 0 shares identical points only.
    """

    num_directions: int = 2048
    num_clusters: int = 120
    num_representatives: int | None = None
    num_neighbours: int = 10
    tile: int = 8
    seed: int = 0
    representatives_per_batch: int = 32
    representatives_per_chunk: int = 1024
    num_threads: int | None = None
    point_cells: int = 64

    def check(self) -> None:
        """Raise ValueError naming the first bad setting."""
        for name in (
            "num_directions",
            "num_clusters",
            "num_neighbours",
            "tile",
            "representatives_per_batch",
            "representatives_per_chunk",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.point_cells < 0:
            raise ValueError(f"point_cells must be >= 0, got {self.point_cells}")
        if (self.num_threads or 1) < 1:
            raise ValueError(f"num_threads must be >= 1, got {self.num_threads}")
        if self.num_representatives is not None and self.num_representatives < 1:
            raise ValueError(f"representatives must be >= 1, got {self.num_representatives}")

    def representatives(self, num_pixels: int) -> int:
        """Representatives at a resolution of `num_pixels`."""
        return self.num_representatives or max(1, round(40000 * num_pixels / REFERENCE_PIXELS))

    def parameters(self) -> dict[str, int]:
        """The settings that change the cache, as cache-layer parameters."""
        return {
            "directions": self.num_directions,
            "clusters": self.num_clusters,
            "representatives": self.num_representatives or 0,
            "neighbours": self.num_neighbours,
            "tile": self.tile,
            "gatherSeed": self.seed,
            "pointCells": self.point_cells,
        }


def set_sizes(view: GBuffer, settings: GatherSettings) -> dict[str, int]:
    """Clusters per tile of each set, split by the camera's diffuse-to-specular energy ratio.

    A set whose share rounds to no cluster is not baked (the diffuse set always gets one).
    """
    height, width = view.image_size
    per_tile = settings.representatives(height * width) / (height * width) * settings.tile**2
    glossy = round(per_tile * glossy_share(view))
    sizes = {"diffuse": max(1, round(per_tile) - glossy), "glossy": glossy}
    return {name: count for name, count in sizes.items() if count > 0}


@per_process
def gather_inputs(shot: ShotSpec, texture_samples: int) -> tuple[Tracer, np.ndarray, GBuffer]:
    """The shot's BVH, triangle tangents and view samples (one per pixel centre), built once per process."""
    scene, _ = load_shot(shot)
    tangents = triangle_tangents(scene.geometry.positions, scene.geometry.uvs)
    return shot_tracer(shot), tangents, view_samples(shot, texture_samples)


def _gather_chunk(spec: ChunkSpec) -> dict[str, np.ndarray]:
    """Gather and cluster the representatives of chunk `spec` (set `spec.name`, view samples in
    parameter 'samples'); batches on `chunk_threads()` threads."""
    scene, _ = load_shot(spec.shot)
    tracer, tangents, view = gather_inputs(spec.shot, spec.param("textureSamples"))
    samples = np.asarray(spec.param("samples"), np.int64)
    seed, per_batch = spec.param("gatherSeed"), spec.param("representativesPerBatch")
    position_weight = 2.0 / max(scene.diagonal, 1e-12)
    directions_u = sobol(spec.param("directions"), 2, seed)
    shifts = torch.from_numpy(np.random.default_rng(seed).random((view.num_samples, 2), np.float32))

    def work(start: int) -> ClusteredGathers:
        batch = torch.from_numpy(samples[start : start + per_batch])
        points = gather(scene, tracer, tangents, view, batch, spec.name, directions_u, shifts[batch])
        return cluster_gathers(points, spec.param("clusters"), position_weight)

    # torch on one thread per batch: the many small ops of the clustering ran ~100x slower with
    # intra-op threads on a busy machine.
    with torch_threads(1), ThreadPoolExecutor(spec.option("threads") or chunk_threads()) as pool:
        # An empty chunk (a camera that sees only sky) is one empty batch: empty arrays of each field.
        parts = list(pool.map(work, range(0, samples.size, per_batch) or [0]))
    arrays = {name: np.concatenate([getattr(p, name) for p in parts]) for name in _FIELD_DTYPES}
    arrays["counts"] = np.concatenate([p.counts for p in parts])
    return arrays


def bake_gather(
    scene: Scene,
    camera: Camera,
    out_dir: str | Path,
    stem: str,
    supersampling: int = 2,
    texture_samples: int = 2,
    time_code: float | None = None,
    settings: GatherSettings = GatherSettings(),
    progress: bool | None = None,
) -> Path:
    """Bake the clustered-gather cache of `camera`; returns the cache layer's path.

    Args:
        supersampling: of the direct part (indirect light has one view sample per pixel centre).
        texture_samples: material samples per sub-sample side (texture filtering).
        time_code: the time the scene was read at.
        settings: directions, clusters, representatives.
        progress: show progress bars (None: when stderr is a terminal).

    Raises:
        ValueError: bad settings (see `GatherSettings.check`).
    """
    settings.check()
    bake = start_indirect_bake(
        scene, camera, out_dir, stem, "gather", settings.parameters(), supersampling, texture_samples, time_code
    )
    chunk_dir = bake.chunk_dir

    shot = ShotSpec.of(scene, camera, time_code)
    _, _, view = gather_inputs(shot, texture_samples)
    parameters = (
        ("textureSamples", texture_samples),
        ("directions", settings.num_directions),
        ("clusters", settings.num_clusters),
        ("gatherSeed", settings.seed),
        ("representativesPerBatch", settings.representatives_per_batch),
    )
    position_weight = 2.0 / max(scene.diagonal, 1e-12)
    payloads = [
        bake.payload(stem, "viewPixels", view.pixel_index.numpy()),
        bake.payload(stem, "viewAlbedo", diffuse_albedo(view.params).numpy().astype(np.float32)),
    ]
    clustered: dict[str, dict[str, np.ndarray]] = {}
    for lobe, clusters_per_tile in set_sizes(view, settings).items():
        with torch_threads(1):
            samples = choose_representatives(view, clusters_per_tile, settings.tile, position_weight)
        specs = [
            ChunkSpec(
                shot,
                lobe,
                parameters + (("samples", tuple(samples[first:last].tolist())),),
                first,
                last,
                (("threads", settings.num_threads),),
            )
            for first, last in chunk_ranges(samples.size, settings.representatives_per_chunk)
        ]
        chunks = [
            load_chunk(path)
            for path in run_chunks(_gather_chunk, specs, chunk_dir, f"{lobe} gathers", "reps", progress)
        ]
        clustered[lobe] = {name: np.concatenate([c[name] for c in chunks]) for name in (*_FIELD_DTYPES, "counts")}
        weights = reconstruction_weights(view, samples, settings.num_neighbours, position_weight)
        payloads.append(bake.payload(stem, f"{lobe}Neighbours", weights.neighbours.astype(np.int32)))
        payloads.append(bake.payload(stem, f"{lobe}Rbf", weights.rbf))
    cell_size = scene.diagonal / settings.point_cells if settings.point_cells else 0.0
    return bake.finish(payloads + _shared_point_payloads(bake, stem, clustered, cell_size))


def _shared_point_payloads(
    bake: IndirectBake, stem: str, clustered: dict[str, dict[str, np.ndarray]], cell_size: float
) -> list[Payload]:
    """Both sets' clustered gathers (chunk fields, concatenated) -> shared points and CSR payloads."""
    fields = {name: np.concatenate([c[name] for c in clustered.values()]) for name in _FIELD_DTYPES}
    points, index = share_points(fields["position"], fields["normal"], fields["albedo"], fields["object"], cell_size)
    payloads = [
        bake.payload(stem, f"gather{name.capitalize()}", getattr(points, name).astype(_FIELD_DTYPES[name]))
        for name in ("position", "normal", "albedo", "object")
    ]
    sizes = [c["object"].size for c in clustered.values()]
    for (lobe, arrays), part in zip(clustered.items(), np.split(index, np.cumsum(sizes)[:-1]), strict=True):
        offsets, columns, weight = merge_entries(arrays["counts"], part, arrays["weight"], points.object.size)
        payloads += [
            bake.payload(stem, f"{lobe}Offsets", offsets),
            bake.payload(stem, f"{lobe}Index", columns.astype(np.int32)),
            bake.payload(stem, f"{lobe}Weight", weight),
        ]
    return payloads
