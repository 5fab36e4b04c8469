"""Visibility cuts per lattice vertex (Cheslack-Postava et al. 2008, section 3.2), computed in scheduler chunks.

Per vertex: one shadow ray (Embree) towards every leaf light above the vertex's geometric
horizon (below it the visibility is 0: the surface itself hides those lights; an indirect-mode
leaf, a surface point, is also 0 when the vertex is behind it), summed up the tree to node means
and variances, and cut from the root down to the nodes with |C| var <= sigma^2
(`relight_torch.cuts.cuts.variance_cut_mask`). A chunk stores each vertex's cut size, its nodes
(ascending) and their means.

Env: the function is the binary visibility, means quantised to 8 bits. Indirect: as in Cheslack-Postava et al. 2008
the geometry term is folded in: the function is V G, G = A cos_leaf / max(d^2, A / 2 pi) the solid
angle of the leaf's patch seen from the vertex (the bound: at most a hemisphere), scaled by
L / (2 pi) (`relight_torch.cuts.cuts.INDIRECT_SCALE`) so that sigma keeps its meaning (a vertex
enclosed by surfaces sees about 2 pi sr in all, 2 pi / L per leaf), means stored as float16.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pipeline.bake.cuts.lights import sphere_directions, surface_points
from pipeline.bake.cuts.tree import build_leaf_order
from pipeline.bake.cuts.vertices import Lattice, build_lattice
from pipeline.bake.deep_framebuffer import grid_rays
from pipeline.bake.scheduler import ChunkSpec, ShotSpec, load_shot, per_process, shot_tracer
from pipeline.tracing import Tracer
from relight_torch.cuts.cuts import MEAN_LEVELS, cuts_from_mask, indirect_scale, variance_cut_mask
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
def cuts_setup(shot: ShotSpec, parameters: tuple[tuple[str, object], ...]) -> CutsSetup:
    """Light points, their tree order and the vertex lattice of the shot's camera (cached per process).

    Parameters used: mode, lights, supersampling, latticeEdge (fraction of the scene's
    bounding-box diagonal), latticeMax, treeK (indirect: K of the geometric metric), beta (the
    data-driven tree's blend, 1 = geometric only) and pilots (its pilot vertices).
    """
    values = dict(parameters)
    scene, camera = load_shot(shot)
    corners = scene.geometry.positions
    diagonal = float(np.linalg.norm(corners.reshape(-1, 3).max(axis=0) - corners.reshape(-1, 3).min(axis=0)))
    origins, rays = grid_rays(camera, int(values["supersampling"]))
    hits = shot_tracer(shot).intersect(origins, rays)
    lattice = build_lattice(
        corners,
        hits.triangle_id[hits.hit],
        hits.barycentrics[hits.hit],
        camera.world_from_camera[:3, 3],
        float(values["latticeEdge"]) * diagonal,
        int(values["latticeMax"]),
    )
    if values["mode"] == "env":
        directions, weights = sphere_directions(int(values["lights"]))
        leaves = {"Directions": directions, "Weights": weights}
        features = directions
    else:
        leaves = surface_points(scene, int(values["lights"]))
        features = np.concatenate((float(values["treeK"]) / diagonal * leaves["Position"], leaves["Normal"]), axis=1)
    beta = float(values["beta"])
    if beta < 1.0:
        features = data_driven_features(
            features, pilot_visibility(shot_tracer(shot), lattice, leaves, int(values["pilots"])), beta
        )
    order = build_leaf_order(features)
    return CutsSetup(values["mode"], {name: array[order] for name, array in leaves.items()}, lattice)


def pilot_visibility(tracer: Tracer, lattice: Lattice, leaves: dict[str, np.ndarray], num_pilots: int) -> np.ndarray:
    """(L, M) the light visibility vectors of Cheslack-Postava et al. 2008's data-driven tree: each light's visibility
    from M pilot vertices, evenly spaced through the lattice (the paper averages M vertex clusters;
    a spaced subset is the simplest subsample of the full vector)."""
    pilots = np.unique(np.linspace(0, lattice.num_vertices - 1, min(num_pilots, lattice.num_vertices)).astype(np.int64))
    return leaf_visibility(tracer, lattice.position[pilots], lattice.normal[pilots], leaves).T


def data_driven_features(geometric: np.ndarray, visibility: np.ndarray, beta: float) -> np.ndarray:
    """Features whose squared distance is Cheslack-Postava et al. 2008's blend (1 - beta) d_v + beta d_g (eq. 12).

    The paper scales d_v by (K^2 + 1) A^2 / M to bring it near d_g; here both parts are scaled
    to unit total variance over the lights instead, which does that normalisation exactly.
    """

    def unit(features: np.ndarray) -> np.ndarray:
        spread = float(np.square(features - features.mean(axis=0)).sum(axis=1).mean())
        return features / np.sqrt(max(spread, 1e-30))

    return np.concatenate((np.sqrt(beta) * unit(geometric), np.sqrt(1.0 - beta) * unit(visibility)), axis=1)


def leaf_visibility(
    tracer: Tracer, position: np.ndarray, normal: np.ndarray, leaves: dict[str, np.ndarray]
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
    blocked = tracer.occluded(
        origins, np.ascontiguousarray(directions[vertex, light], np.float32), t_far.astype(np.float32)
    )
    visibility = np.zeros(above.shape, np.float32)
    visibility[vertex[~blocked], light[~blocked]] = 1.0
    return visibility


def visibility_chunk(spec: ChunkSpec) -> dict[str, np.ndarray]:
    """The visibility cuts of lattice vertices [spec.start, spec.stop): counts, nodes, means."""
    setup = cuts_setup(spec.shot, spec.parameters)
    rows = slice(spec.start, spec.stop)
    position = setup.lattice.position[rows]
    values = torch.from_numpy(
        leaf_visibility(shot_tracer(spec.shot), position, setup.lattice.normal[rows], setup.leaves)
    )
    num_leaves = values.shape[1]
    if setup.mode == "indirect":
        values = values * torch.from_numpy(leaf_solid_angle(position, setup.leaves)) / indirect_scale(num_leaves)
    tree = LightTree.of(num_leaves)
    means = tree.aggregate_batch(values) / tree.size
    variances = (tree.aggregate_batch(values.square()) / tree.size - means.square()).clamp_min(0.0)
    cuts = cuts_from_mask(variance_cut_mask(tree, variances, float(spec.param("sigma"))), means.unsqueeze(-1))
    node_dtype = np.uint16 if tree.num_nodes <= np.iinfo(np.uint16).max + 1 else np.uint32
    stored = cuts.values[:, 0].numpy()
    return {
        "counts": cuts.sizes().numpy().astype(np.uint32),
        "nodes": cuts.nodes.numpy().astype(node_dtype),
        "means": (np.rint(stored * MEAN_LEVELS).astype(np.uint8) if setup.mode == "env" else stored.astype(np.float16)),
    }


def leaf_solid_angle(position: np.ndarray, leaves: dict[str, np.ndarray]) -> np.ndarray:
    """(V, L) float32 solid angle A cos_leaf / max(d^2, A / 2 pi) of every surface-point leaf's patch
    seen from V points (0 from behind it)."""
    offset = leaves["Position"][None] - position[:, None]
    distance2 = np.square(offset).sum(axis=-1)
    cosine = -np.einsum("vlk,lk->vl", offset, leaves["Normal"]) / np.sqrt(np.maximum(distance2, 1e-30))
    area = leaves["Area"][None]
    return (area * np.clip(cosine, 0.0, None) / np.maximum(distance2, area / (2.0 * np.pi))).astype(np.float32)
