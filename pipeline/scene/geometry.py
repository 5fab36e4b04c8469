"""Walk a stage's renderable gprims into one world-space triangle soup (`Geometry`).

What is rendered: every Mesh and implicit gprim (see `tessellate`) whose purpose is default or
render and that is not invisible, including instance proxies of instanceable prims, and every
instance of every PointInstancer (its subtree is pruned from the walk and its prototypes are
placed by `ComputeInstanceTransformsAtTime`, which honours masks and the prototype root's own
transform; instancers nest). Inside a prototype, visibility is read from the prototype root down
only: a hidden "Prototypes" scope above the roots does not hide the instances.

Subdivision meshes (see `subdivision`) are refined to the level their placements need at the
stage's cameras; the refined surface is shared by every placement at that level.

Each placed gprim is one `SceneObject`. Materials come per face from the gprim's bound material
and its `materialBind` GeomSubsets, through `MaterialLibrary.id_for`. World positions use the
column-vector matrix; normals its inverse transpose; a mirroring transform (negative determinant)
re-winds the triangles so that the geometric and shading normals keep agreeing.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from pxr import Usd, UsdGeom, UsdShade

from pipeline.errors import warn
from pipeline.scene import dicing
from pipeline.scene.primvars import read_primvar
from pipeline.scene.subdivision import Refinement, is_subdivision, read_subdivision_mesh
from pipeline.scene.tessellate import Surface, implicit_surface, is_implicit, mesh_surface
from pipeline.scene.types import Camera, Geometry, SceneObject
from relight_torch import xform

# A triangle is degenerate when |cross| <= this times its longest squared edge (a relative
# zero: repeated or collinear float32 points, not thin slivers).
_DEGENERATE_RELATIVE_AREA = 1e-12


@dataclass(frozen=True)
class _Placement:
    """One gprim and the world transforms of all its placements.

    Attributes:
        prim: the Mesh or implicit gprim (an instance proxy for instanced prims).
        world_from_local: (I, 4, 4) float64 column-vector transforms, one per placement.
        paths: (I,) object paths.
    """

    prim: Usd.Prim
    world_from_local: np.ndarray
    paths: list[str]


class _Walker:
    """Finds every rendered gprim placement of a stage at one time code."""

    def __init__(self, time: Usd.TimeCode, warnings: list[str]):
        self.time = time
        self.warnings = warnings
        self.xform_cache = UsdGeom.XformCache(time)

    def _rendered(self, prim: Usd.Prim, prototype_root: Usd.Prim | None) -> bool:
        """Purpose default/render and visible (from the prototype root down, inside one)."""
        imageable = UsdGeom.Imageable(prim)
        if imageable.ComputePurpose() not in (UsdGeom.Tokens.default_, UsdGeom.Tokens.render):
            return False
        if prototype_root is None:
            return imageable.ComputeVisibility(self.time) != UsdGeom.Tokens.invisible
        stop = prototype_root.GetParent()
        while prim and prim != stop:
            if UsdGeom.Imageable(prim).GetVisibilityAttr().Get(self.time) == UsdGeom.Tokens.invisible:
                return False
            prim = prim.GetParent()
        return True

    def _base_from_prim(self, prim: Usd.Prim, prototype_root: Usd.Prim | None) -> np.ndarray:
        """(4, 4) transform from the prim's space to the world, or to its prototype root's space."""
        return xform.world_from_local(self.xform_cache, prim, prototype_root)

    def _placed(
        self, prim: Usd.Prim, world_from_base: np.ndarray, prototype_root: Usd.Prim | None
    ) -> np.ndarray | None:
        """(I, 4, 4) world transforms of `prim`'s placements; None, with a warning, when an xformOp
        of it or an ancestor is not a transform (the prim is skipped, as a mesh with bad indices is)."""
        try:
            return world_from_base @ self._base_from_prim(prim, prototype_root)
        except ValueError as error:
            warn(f"{error}; skipped", self.warnings)
            return None

    def walk(
        self, root: Usd.Prim, world_from_base: np.ndarray, base_paths: list[str], prototype_root: Usd.Prim | None = None
    ) -> Iterator[_Placement]:
        """Yield the gprim placements under `root`.

        Args:
            root: where to start (the pseudo-root, or a PointInstancer prototype root).
            world_from_base: (I, 4, 4) placements of the base space (identity for the stage).
            base_paths: (I,) object-path prefixes of those placements ('' for the stage).
            prototype_root: the prototype root when walking a prototype, else None.
        """
        predicate = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
        prims = iter(Usd.PrimRange(root, predicate))
        for prim in prims:
            if prim.IsA(UsdGeom.PointInstancer):
                prims.PruneChildren()
                if not self._rendered(prim, prototype_root):
                    continue
                world_from_instancer = self._placed(prim, world_from_base, prototype_root)
                if world_from_instancer is not None:
                    yield from self._instances(UsdGeom.PointInstancer(prim), world_from_instancer, base_paths)
            elif (prim.IsA(UsdGeom.Mesh) or is_implicit(prim)) and self._rendered(prim, prototype_root):
                world_from_local = self._placed(prim, world_from_base, prototype_root)
                if world_from_local is not None:
                    yield _Placement(prim, world_from_local, [f"{b}{prim.GetPath()}" for b in base_paths])

    def _instances(
        self, instancer: UsdGeom.PointInstancer, world_from_instancer: np.ndarray, base_paths: list[str]
    ) -> Iterator[_Placement]:
        """Yield the placements of every prototype of a PointInstancer (I outer placements)."""
        path = instancer.GetPath()
        transforms = instancer.ComputeInstanceTransformsAtTime(self.time, self.time)
        proto_indices = np.asarray(instancer.GetProtoIndicesAttr().Get(self.time) or [], np.int64)
        mask = np.asarray(instancer.ComputeMaskAtTime(self.time) or [], bool)
        instance_ids = np.nonzero(mask)[0] if mask.size else np.arange(proto_indices.size)
        if transforms is None or len(transforms) != instance_ids.size:
            # USD computes no transforms at all when the arrays disagree or an index is invalid.
            warn(f"point instancer {path}: positions, protoIndices and prototypes do not match; skipped", self.warnings)
            return
        instancer_from_instance = np.array(transforms, np.float64).reshape(-1, 4, 4).transpose(0, 2, 1)
        proto_indices = proto_indices[instance_ids]
        stage = instancer.GetPrim().GetStage()
        prototypes = instancer.GetPrototypesRel().GetForwardedTargets()
        for index, target in enumerate(prototypes):
            selected = np.nonzero(proto_indices == index)[0]
            prototype = stage.GetPrimAtPath(target)
            if selected.size == 0 or not prototype:
                continue
            world_from_prototype = (world_from_instancer[:, None] @ instancer_from_instance[selected][None]).reshape(
                -1, 4, 4
            )
            paths = [f"{b}{path}[{i}]" for b in base_paths for i in instance_ids[selected]]
            yield from self.walk(prototype, world_from_prototype, paths, prototype_root=prototype)


def _invertible(placement: _Placement, warnings: list[str]) -> _Placement | None:
    """The placement without its non-finite or singular transforms (a zero scale), with a warning
    naming the prim; None when none is left. Surface refinement inverts them (`dicing`), and such a
    placement has no area to render anyway."""
    linear = placement.world_from_local[:, :3, :3]
    finite = np.isfinite(placement.world_from_local).all(axis=(1, 2))
    with np.errstate(invalid="ignore", over="ignore"):
        determinant = np.linalg.det(np.where(finite[:, None, None], linear, 0.0))
    keep = finite & (determinant != 0) & np.isfinite(determinant)
    if keep.all():
        return placement
    warn(
        f"{placement.prim.GetPath()}: world transform of {int((~keep).sum())} of {len(keep)} placements is not "
        "finite and invertible (a zero scale?); skipped",
        warnings,
    )
    if not keep.any():
        return None
    return _Placement(
        placement.prim, placement.world_from_local[keep], [p for p, k in zip(placement.paths, keep, strict=True) if k]
    )


def _place(surface: Surface, world_from_local: np.ndarray):
    """Transform a surface to each of I placements.

    Returns:
        positions (I*T, 3, 3) float64, normals (I*T, 3, 3) float64 (unnormalised, zero where
        unknown), uvs (I*T, 3, 2); triangles of a mirrored placement are re-wound.
    """
    count, num_triangles = len(world_from_local), surface.num_triangles
    rotation = world_from_local[:, :3, :3]
    det = np.linalg.det(rotation)
    invertible = np.abs(det) > 0
    normal_from_local = np.zeros_like(rotation)
    normal_from_local[invertible] = np.linalg.inv(rotation[invertible]).transpose(0, 2, 1)
    local_positions = surface.positions.reshape(-1, 3).astype(np.float64)
    local_normals = surface.normals.reshape(-1, 3).astype(np.float64)
    positions = np.empty((count,) + local_positions.shape)
    normals = np.empty_like(positions)
    # One (3 T, 3) x (3, 3) BLAS product per placement: numpy's batched matmul does not use BLAS
    # for the broadcast (1, 3 T, 3) x (I, 3, 3) product and is several times slower.
    for index in range(count):
        np.matmul(local_positions, rotation[index].T, out=positions[index])
        positions[index] += world_from_local[index, :3, 3]
        np.matmul(local_normals, normal_from_local[index].T, out=normals[index])
    positions = positions.reshape(count, num_triangles, 3, 3)
    normals = normals.reshape(count, num_triangles, 3, 3)
    uvs = np.broadcast_to(surface.uvs, (count, num_triangles, 3, 2))
    mirrored = det < 0
    if mirrored.any():
        winding = [0, 2, 1]
        positions[mirrored] = positions[mirrored][:, :, winding]
        normals[mirrored] = normals[mirrored][:, :, winding]
        uvs = np.where(mirrored[:, None, None, None], uvs[:, :, winding], uvs)
    return positions.reshape(-1, 3, 3), normals.reshape(-1, 3, 3), uvs.reshape(-1, 3, 2)


def _finish_triangles(positions: np.ndarray, normals: np.ndarray, uvs: np.ndarray):
    """Drop degenerate/non-finite triangles; replace unknown normals by the face normal.

    Args:
        positions, normals: (N, 3, 3) float64 world space. uvs: (N, 3, 2).

    Returns:
        (keep (N,) bool, positions (K, 3, 3), normals (K, 3, 3) unit, uvs (K, 3, 2)) float32.
    """
    cross = np.cross(positions[:, 1] - positions[:, 0], positions[:, 2] - positions[:, 0])
    with np.errstate(invalid="ignore", over="ignore"):
        twice_area = np.linalg.norm(cross, axis=-1)
        edges = positions - positions[:, [2, 0, 1]]
        longest_edge2 = np.max(np.sum(np.square(edges, out=edges), -1), -1)
        del edges
        keep = np.isfinite(twice_area) & (twice_area > _DEGENERATE_RELATIVE_AREA * longest_edge2)
        keep &= np.isfinite(positions).all(axis=(1, 2))
    all_kept = bool(keep.all())
    face_normal = cross[keep] / twice_area[keep, None]
    del cross
    normals = normals if all_kept else normals[keep]
    if not np.isfinite(normals).all():
        normals = np.where(np.isfinite(normals), normals, 0.0)
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    unit = np.where(length > 0, normals / np.where(length > 0, length, 1.0), face_normal[:, None])
    uvs = np.nan_to_num(uvs if all_kept else uvs[keep], nan=0.0, posinf=0.0, neginf=0.0)
    kept_positions = positions if all_kept else positions[keep]
    return keep, kept_positions.astype(np.float32), unit.astype(np.float32), uvs.astype(np.float32)


def _display_color(prim: Usd.Prim, time: Usd.TimeCode) -> tuple[np.ndarray | None, str | None]:
    """The gprim's displayColor as one colour: ((3,) float32 or None, interpolation of a
    non-constant colour that had to be averaged, else None)."""
    primvar = read_primvar(prim, "displayColor", time)
    if primvar is None or len(primvar[0]) == 0 or primvar[0].shape[1] != 3:
        return None, None
    values, interpolation = primvar
    averaged = None if np.all(values == values[0]) else interpolation
    return values.mean(axis=0).astype(np.float32), averaged


def _bound_material(prim: Usd.Prim) -> UsdShade.Material | None:
    material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
    return material if material else None


def _face_material_ids(
    prim: Usd.Prim, num_faces: int, display_color: np.ndarray | None, library, time: Usd.TimeCode, warnings: list[str]
) -> np.ndarray:
    """(F,) int32 material id of each authored face: the gprim's binding, then its
    `materialBind` GeomSubsets."""
    path = str(prim.GetPath())
    ids = np.full(num_faces, library.id_for(_bound_material(prim), display_color, path), np.int32)
    if not prim.IsA(UsdGeom.Mesh):
        return ids
    for subset in UsdShade.MaterialBindingAPI(prim).GetMaterialBindSubsets():
        faces = np.asarray(subset.GetIndicesAttr().Get(time) or [], np.int64)
        if faces.size and (faces.min() < 0 or faces.max() >= num_faces):
            warn(f"GeomSubset {subset.GetPath()}: face indices outside the mesh's {num_faces} faces; ignored", warnings)
            continue
        ids[faces] = library.id_for(_bound_material(subset.GetPrim()), display_color, path)
    return ids


# Triangles placed at once: bounds the float64 temporaries of `_place` and `_finish_triangles`
# (about 400 bytes a triangle) however many instances a prototype has.
_PLACE_TRIANGLES = 1 << 20


def _soup_parts(
    surface: Surface, material_ids: np.ndarray, world_from_local: np.ndarray, object_ids: np.ndarray
) -> Iterator[tuple[int, tuple[np.ndarray, ...]]]:
    """One gprim's triangles at its I placements, in chunks of placements of at most about
    `_PLACE_TRIANGLES` triangles.

    Args:
        surface: the gprim's local triangles (T). material_ids: (T,) per triangle.
        world_from_local: (I, 4, 4) placements. object_ids: (I,) their object ids.

    Yields:
        (number of triangles dropped, (positions, normals, uvs, material_ids, object_ids)) per chunk.
    """
    step = max(1, _PLACE_TRIANGLES // max(surface.num_triangles, 1))
    for first in range(0, len(world_from_local), step):
        chunk = world_from_local[first : first + step]
        keep, positions, normals, uvs = _finish_triangles(*_place(surface, chunk))
        chunk_ids = np.repeat(object_ids[first : first + step].astype(np.int32), surface.num_triangles)
        part = (positions, normals, uvs, np.tile(material_ids, len(chunk))[keep], chunk_ids[keep])
        yield int((~keep).sum()), part


class _Surfaces:
    """Each gprim's surface, built once per source prim (and per subdivision level)."""

    def __init__(self, time: Usd.TimeCode, views: list[dicing.View], warnings: list[str]):
        self.time, self.views, self.warnings = time, views, warnings
        self._surfaces: dict[str, Surface | None] = {}
        self._subdivision: dict[str, Refinement | None] = {}
        self._budget_warned: set[str] = set()

    def get(self, prim: Usd.Prim, key: str, world_from_local: np.ndarray) -> list[tuple[Surface | None, np.ndarray]]:
        """The surfaces of `prim` (source path `key`) for placements (I, 4, 4): (surface, the (K,)
        placement rows it serves) per subdivision level the placements need (one for other gprims)."""
        if prim.IsA(UsdGeom.Mesh) and is_subdivision(UsdGeom.Mesh(prim), self.time):
            if key not in self._subdivision:
                mesh = read_subdivision_mesh(UsdGeom.Mesh(prim), self.time, self.warnings)
                self._subdivision[key] = None if mesh is None else Refinement(mesh)
            refinement = self._subdivision[key]
            if refinement is not None:
                levels, budget_warning = refinement.choose_levels(world_from_local, self.views)
                if budget_warning and key not in self._budget_warned:
                    self._budget_warned.add(key)
                    warn(budget_warning, self.warnings)
                return [
                    (refinement.surface(level) if level > 0 else self._cage(prim, key), np.flatnonzero(levels == level))
                    for level in np.unique(levels).tolist()
                ]
        return [(self._cage(prim, key), np.arange(len(world_from_local)))]

    def _cage(self, prim: Usd.Prim, key: str) -> Surface | None:
        """The gprim as authored: a mesh's (unrefined) faces, or an implicit gprim's tessellation."""
        if key not in self._surfaces:
            self._surfaces[key] = (
                mesh_surface(UsdGeom.Mesh(prim), self.time, self.warnings)
                if prim.IsA(UsdGeom.Mesh)
                else implicit_surface(prim, self.time)
            )
        return self._surfaces[key]


def read_geometry(
    stage: Usd.Stage, time: Usd.TimeCode, library, warnings: list[str], cameras: dict[str, Camera] | None = None
) -> tuple[Geometry, list[SceneObject]]:
    """The stage's rendered gprims as one world-space triangle soup.

    Args:
        stage: the composed stage.
        time: time code for transforms, points and attributes.
        library: a `pipeline.scene.materials.MaterialLibrary` (anything with `id_for(material,
            display_color, prim_path) -> int`).
        warnings: sink for one-line warnings.
        cameras: the cameras subdivision surfaces are refined for (`dicing`); None or empty
            for the fallback level.

    Returns:
        (geometry, objects): `geometry.object_ids` index `objects`; the geometry may be empty.
    """
    walker = _Walker(time, warnings)
    surfaces = _Surfaces(time, dicing.views_from_cameras(cameras or {}), warnings)
    averaged_keys: set[str] = set()
    # First every placement's surfaces (the levels chosen), then the soup written straight into
    # arrays sized for all of them: no list of parts held beside the joined soup (the small parts
    # of far instances would stay in the heap and double the peak).
    jobs: list[tuple[str, str, Surface, np.ndarray, np.ndarray, np.ndarray]] = []
    objects: list[SceneObject] = []
    for placement in walker.walk(stage.GetPseudoRoot(), np.eye(4)[None], [""]):
        placement = _invertible(placement, warnings)
        if placement is None:
            continue
        prim = placement.prim
        source = prim.GetPrimInPrototype() if prim.IsInstanceProxy() else prim
        key = str(source.GetPath())
        groups = [
            (surface, rows)
            for surface, rows in surfaces.get(prim, key, placement.world_from_local)
            if surface is not None and surface.num_triangles
        ]
        if not groups:
            continue
        display_color, averaged = _display_color(prim, time)
        if averaged and key not in averaged_keys:  # once per surface, not per instance
            averaged_keys.add(key)
            warn(f"{prim.GetPath()}: per-{averaged} displayColor averaged to one colour", warnings)
        face_ids = _face_material_ids(prim, groups[0][0].num_faces, display_color, library, time, warnings)
        double_sided = bool(UsdGeom.Gprim(prim).GetDoubleSidedAttr().Get(time))
        for surface, rows in groups:
            world_from_local = placement.world_from_local[rows]
            jobs.append(
                (key, str(prim.GetPath()), surface, face_ids[surface.face_ids], world_from_local, len(objects) + rows)
            )
        objects.extend(SceneObject(path, double_sided) for path in placement.paths)
    return _write_soup(jobs, warnings), objects


def _write_soup(
    jobs: list[tuple[str, str, Surface, np.ndarray, np.ndarray, np.ndarray]], warnings: list[str]
) -> Geometry:
    """The soup of every (surface key, prim path, surface, material ids (T,), placements (I, 4, 4),
    object ids (I,)) job, written part by part into arrays sized for all their triangles (the pages
    of the triangles dropped as degenerate are never touched), with a warning per surface that
    lost triangles."""
    total = sum(surface.num_triangles * len(placements) for _, _, surface, _, placements, _ in jobs)
    joined = [
        np.empty((total, 3, 3), np.float32),
        np.empty((total, 3, 3), np.float32),
        np.empty((total, 3, 2), np.float32),
        np.empty(total, np.int32),
        np.empty(total, np.int32),
    ]
    dropped: dict[str, list] = {}  # surface key -> [first prim path, triangles dropped]
    start = 0
    for key, path, surface, material_ids, placements, object_ids in jobs:
        for num_dropped, part in _soup_parts(surface, material_ids, placements, object_ids):
            if num_dropped:
                dropped.setdefault(key, [path, 0])[1] += num_dropped
            stop = start + part[0].shape[0]
            for target, array in zip(joined, part, strict=True):
                target[start:stop] = array
            start = stop
    for path, count in dropped.values():
        warn(f"{path}: dropped {count} degenerate or non-finite triangles", warnings)
    positions, normals, uvs, material_ids, object_ids = (array[:start] for array in joined)
    return Geometry(positions=positions, normals=normals, uvs=uvs, material_ids=material_ids, object_ids=object_ids)
