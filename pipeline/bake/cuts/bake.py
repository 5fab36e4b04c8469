"""`relight bake --method cuts`: the direct cache plus Cheslack-Postava et al. 2008's light tree and visibility cuts.

Writes into OUT, beside the direct method's payloads (`pipeline.bake.direct.bake`), the leaf lights
in tree order (post-order leaves left to right):
    env:      <stem>.cutsLeafDirections.npy (L, 3) float32 unit world directions,
              <stem>.cutsLeafWeights.npy (L,) float32 their solid angles (sr)
    indirect: <stem>.cutsLeaf{Position,Normal,Albedo,Emission}.npy (L, 3) float32,
              <stem>.cutsLeafArea.npy (L,) float32, <stem>.cutsLeafObjectId.npy (L,) int32: surface
              points (the transfer method's gather cloud) with their area and object
and the visibility cuts:
    <stem>.cutsOffsets.npy          (V + 1,) uint32 (uint64 past 2^32 entries) CSR offsets of
                                    the V lattice vertices' cuts
    <stem>.cutsNodes.npy            (nnz,) uint16 (uint32 over 65,535 nodes) post-order node of
                                    each cut entry, ascending within a vertex
    <stem>.cutsMeans.npy            (nnz,) env: uint8 mean visibility, round(<v> * 255); indirect:
                                    float16 mean of V G / (2 pi / L) (`visibility` module)
    <stem>.cutsSampleVertices.npy   (N, 3) uint32 lattice vertices around each covered sub-sample
                                    of the deep framebuffer (same order)
    <stem>.cutsSampleWeights.npy    (N, 3) float16 their barycentric weights
Visibility cuts are baked in chunks of vertices (`pipeline.bake.scheduler`) kept in
`.<stem>.cuts-<hash>/` until the cache layer is rewritten (method 'cuts').
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.bake.cuts.visibility import cuts_setup, visibility_chunk
from pipeline.bake.indirect import start_indirect_bake
from pipeline.bake.scheduler import ChunkSpec, ShotSpec, chunk_ranges, load_chunk, remember_shot, run_chunks
from pipeline.scene.types import Camera, Scene

MODES = ("env", "indirect")


@dataclass(frozen=True)
class CutsSettings:
    """What the cuts bake computes.

    Attributes:
        mode: 'env' (distant lights on the sphere: dome lights) or 'indirect' (surface points:
            one diffuse bounce of every light).
        num_lights: point lights L, a power of two (the paper: 32K); a power of 4 for 'indirect'.
        sigma: visibility cut threshold, |C| var <= sigma^2 (the paper: 1.5 to 3).
        lattice_edge: longest lattice edge wanted, as a fraction of the scene's bounding-box diagonal.
        lattice_max: most subdivisions per triangle side.
        vertices_per_chunk: lattice vertices per scheduler chunk (memory ~ 100 B x L per vertex).
        tree_k: K of the geometric tree metric (Cheslack-Postava et al. 2008, eq. 10; indirect mode).
        beta: the data-driven tree's blend of geometric and pilot-visibility distances (Cheslack-Postava et al. 2008,
            eq. 12: 0.4 to 0.5); 1 builds the purely geometric tree.
        pilot_vertices: M, vertices whose visibility of every light drives the data-driven tree.
    """

    mode: str = "env"
    num_lights: int = 32768
    sigma: float = 2.0
    lattice_edge: float = 1.0 / 64.0
    lattice_max: int = 64
    vertices_per_chunk: int = 128
    tree_k: float = 30.0
    beta: float = 1.0
    pilot_vertices: int = 1024

    def check(self) -> None:
        """Raise ValueError naming the first bad setting."""
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.num_lights < 2 or self.num_lights & (self.num_lights - 1):
            raise ValueError(f"lights must be a power of two >= 2 (e.g. 32768), got {self.num_lights}")
        if self.mode == "indirect" and self.num_lights.bit_length() % 2 == 0:
            raise ValueError(f"indirect mode needs a power of 4 lights (e.g. 16384), got {self.num_lights}")
        if not 0.0 <= self.beta <= 1.0 or self.pilot_vertices < 1:
            raise ValueError(f"beta must be in [0, 1] and pilot vertices >= 1, got {self.beta}, {self.pilot_vertices}")
        if self.sigma <= 0 or self.lattice_edge <= 0 or self.lattice_max < 1 or self.vertices_per_chunk < 1:
            raise ValueError("sigma and lattice edge must be > 0, lattice max and vertices per chunk >= 1")

    def parameters(self) -> dict[str, object]:
        """The settings that change the cache, as cache-layer parameters."""
        return {
            "cutsMode": self.mode,
            "cutsLights": self.num_lights,
            "cutsSigma": float(self.sigma),
            "cutsLatticeEdge": float(self.lattice_edge),
            "cutsLatticeMax": self.lattice_max,
            "cutsTreeK": float(self.tree_k),
            "cutsBeta": float(self.beta),
            "cutsPilots": self.pilot_vertices,
        }


def bake_cuts(
    scene: Scene,
    camera: Camera,
    out_dir: str | Path,
    stem: str,
    supersampling: int = 2,
    texture_samples: int = 2,
    time_code: float | None = None,
    settings: CutsSettings = CutsSettings(),
) -> Path:
    """Bake the cuts cache of `camera`; returns the cache layer's path.

    Raises:
        ValueError: bad settings (`CutsSettings.check`).
    """
    settings.check()
    bake = start_indirect_bake(
        scene, camera, out_dir, stem, "cuts", settings.parameters(), supersampling, texture_samples, time_code
    )
    shot = ShotSpec.of(scene, camera, time_code)
    remember_shot(shot, scene)
    parameters = (
        ("mode", settings.mode),
        ("treeK", float(settings.tree_k)),
        ("beta", float(settings.beta)),
        ("pilots", settings.pilot_vertices),
        ("lights", settings.num_lights),
        ("supersampling", supersampling),
        ("latticeEdge", float(settings.lattice_edge)),
        ("latticeMax", settings.lattice_max),
        ("sigma", float(settings.sigma)),
    )
    setup = cuts_setup(shot, parameters)
    lattice = setup.lattice
    specs = [
        ChunkSpec(shot, "visibilityCuts", parameters, start, stop)
        for start, stop in chunk_ranges(lattice.num_vertices, settings.vertices_per_chunk)
    ]
    chunks = [
        load_chunk(path) for path in run_chunks(visibility_chunk, specs, bake.chunk_dir, "visibility cuts", "vertices")
    ]
    counts = np.concatenate([chunk["counts"] for chunk in chunks]).astype(np.uint64)
    offsets = np.concatenate(([0], np.cumsum(counts)))
    offsets = offsets.astype(np.uint32 if offsets[-1] < np.iinfo(np.uint32).max else np.uint64)
    sample_vertices = lattice.sample_vertices.astype(np.uint32)
    payloads = [bake.payload(stem, f"cutsLeaf{name}", array) for name, array in setup.leaves.items()]
    payloads += [
        bake.payload(stem, "cutsOffsets", offsets),
        bake.payload(stem, "cutsNodes", np.concatenate([chunk["nodes"] for chunk in chunks])),
        bake.payload(stem, "cutsMeans", np.concatenate([chunk["means"] for chunk in chunks])),
        bake.payload(stem, "cutsSampleVertices", sample_vertices),
        bake.payload(stem, "cutsSampleWeights", lattice.sample_weights.astype(np.float16)),
    ]
    return bake.finish(payloads)
