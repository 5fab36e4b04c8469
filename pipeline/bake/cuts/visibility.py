"""Visibility cuts per lattice vertex (seed 004, section 3.2), computed in scheduler chunks.

Per vertex: one shadow ray (Embree) towards every leaf light above the vertex's geometric
horizon (below it the visibility is 0: the surface itself hides those lights; an indirect-mode
leaf, a surface point, is also 0 when the vertex is behind it), summed up the tree
to node means <v> and variances <v>(1 - <v>) (visibility is binary), and cut from the root down
to the nodes with |C| var <= sigma^2 (`relight_torch.cuts.cuts.variance_cut_mask`). A chunk
stores each vertex's cut size, its nodes (ascending) and the means quantised to 8 bits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pipeline.bake.cuts.lights import sphere_directions, surface_points
from pipeline.bake.cuts.tree import build_leaf_order
from pipeline.bake.cuts.vertices import Lattice, build_lattice
from pipeline.bake.deep_framebuffer import grid_rays
from pipeline.bake.scheduler import ChunkSpec, ShotSpec, chunk_threads, load_shot, per_process
from pipeline.tracing import Tracer
from relight_torch.cuts.cuts import MEAN_LEVELS, cuts_from_mask, variance_cut_mask
from relight_torch.cuts.tree import LightTree


@dataclass(frozen=True)
class CutsSetup:
    """What every chunk and the driver share, derived from the shot and the parameters.

    Attributes:
        mode: 'env' or 'indirect'.
        leaves: the leaf lights in tree order, by payload name (`pipeline.bake.cuts.lights`):
            env 'Directions' (L, 3), 'Weights' (L,); indirect 'Position', 'Normal', 'Albedo',
            'Emission' (L, 3), 'Area' (L,), 'ObjectId' (L,).
        lattice: the refined vertices and the sub-samples' interpolation.
    """

    mode: str
    leaves: dict[str, np.ndarray]
    lattice: Lattice


@per_process
def tracer_for(shot: ShotSpec) -> Tracer:
    """The shot's Embree tracer, built once per process."""
    scene, _ = load_shot(shot)
    return Tracer(scene.geometry, num_threads=chunk_threads())


@per_process
def cuts_setup(shot: ShotSpec, parameters: tuple[tuple[str, object], ...]) -> CutsSetup:
    """Light points, their tree order and the vertex lattice of the shot's camera (cached per process).

    Parameters used: mode, lights, supersampling, latticeEdge (fraction of the scene's
    bounding-box diagonal), latticeMax, treeK (indirect: K of the geometric metric).
    """
    values = dict(parameters)
    scene, camera = load_shot(shot)
    corners = scene.geometry.positions
    diagonal = float(np.linalg.norm(corners.reshape(-1, 3).max(axis=0) - corners.reshape(-1, 3).min(axis=0)))
    if values["mode"] == "env":
        directions, weights = sphere_directions(int(values["lights"]))
        leaves = {"Directions": directions, "Weights": weights}
        features = directions
    else:
        leaves = surface_points(scene, int(values["lights"]))
        features = np.concatenate((float(values["treeK"]) / diagonal * leaves["Position"], leaves["Normal"]), axis=1)
    order = build_leaf_order(features)
    origins, rays = grid_rays(camera, int(values["supersampling"]))
    hits = tracer_for(shot).intersect(origins, rays)
    lattice = build_lattice(corners, hits.triangle_id[hits.hit], hits.barycentrics[hits.hit],
                            camera.world_from_camera[:3, 3], float(values["latticeEdge"]) * diagonal,
                            int(values["latticeMax"]))
    return CutsSetup(values["mode"], {name: array[order] for name, array in leaves.items()}, lattice)


def leaf_visibility(tracer: Tracer, position: np.ndarray, normal: np.ndarray, leaves: dict[str, np.ndarray]
                    ) -> np.ndarray:
    """(V, L) float32 visibility of L leaf lights from V surface points (0 below their horizon).

    Env leaves are distant directions; indirect leaves are surface points, 0 where the vertex is
    behind them, their shadow rays stopped short of them.
    """
    if "Directions" in leaves:
        directions = np.broadcast_to(leaves["Directions"], (position.shape[0], *leaves["Directions"].shape))
        distance = np.full(directions.shape[:2], np.inf, np.float32)
        facing = np.ones(directions.shape[:2], bool)
    else:
        offset = leaves["Position"][None] - position[:, None]
        distance = np.linalg.norm(offset, axis=-1)
        directions = offset / np.maximum(distance, 1e-30)[..., None]
        facing = np.einsum("vlk,lk->vl", directions, leaves["Normal"]) < 0
    above = (np.einsum("vlk,vk->vl", directions, normal) > 0) & facing
    vertex, light = np.nonzero(above)
    origins = (position[vertex] + np.float32(tracer.epsilon) * normal[vertex]).astype(np.float32)
    t_far = distance[vertex, light] * np.float32(1.0 - 1e-4) - np.float32(tracer.epsilon)
    blocked = tracer.occluded(origins, np.ascontiguousarray(directions[vertex, light], np.float32),
                              t_far.astype(np.float32))
    visibility = np.zeros(above.shape, np.float32)
    visibility[vertex[~blocked], light[~blocked]] = 1.0
    return visibility


def visibility_chunk(spec: ChunkSpec) -> dict[str, np.ndarray]:
    """The visibility cuts of lattice vertices [spec.start, spec.stop): counts, nodes, means."""
    setup = cuts_setup(spec.shot, spec.parameters)
    rows = slice(spec.start, spec.stop)
    visibility = leaf_visibility(tracer_for(spec.shot), setup.lattice.position[rows], setup.lattice.normal[rows],
                                 setup.leaves)
    tree = LightTree.of(visibility.shape[1])
    means = tree.aggregate_batch(torch.from_numpy(visibility)) / tree.size
    cuts = cuts_from_mask(variance_cut_mask(tree, means * (1.0 - means), float(spec.param("sigma"))),
                          means.unsqueeze(-1))
    node_dtype = np.uint16 if tree.num_nodes <= np.iinfo(np.uint16).max + 1 else np.uint32
    return {"counts": cuts.sizes().numpy().astype(np.uint32),
            "nodes": cuts.nodes.numpy().astype(node_dtype),
            "means": np.rint(cuts.values[:, 0].numpy() * MEAN_LEVELS).astype(np.uint8)}
