"""The caching cameras of a multiview cache and their deep framebuffers, as one pool of samples.

A cache records K pinhole cameras in a (K, C) float64 table (`CAMERA_COLUMNS`) and one deep
framebuffer per camera. `CachingViews` concatenates the K G-buffers into one pool of samples
(view k's covered sub-samples at rows offsets[k]:offsets[k + 1]) and keeps, per camera, a flat
image of pool rows (-1 where nothing was hit) and of depths (inf there): the correspondence map
projects a point into camera k and reads both at the pixel it lands in.

Projection follows `pipeline.scene.camera` (the tests check the two agree): the camera looks down
its local -Z with +Y up; x_film = focal x / depth, pixel column = ((x_film - x_offset) /
horizontal_aperture + 0.5) W, row = (0.5 - (y_film - y_offset) / vertical_aperture) H.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.gbuffer import GBuffer

CAMERA_COLUMNS = tuple(f"worldFromCamera{r}{c}" for r in range(4) for c in range(4)) + (
    "focalLength",
    "horizontalAperture",
    "verticalAperture",
    "horizontalApertureOffset",
    "verticalApertureOffset",
    "near",
    "far",
    "width",
    "height",
    "kind",
    "group",
)
"""Columns of the (K, C) float64 camera table: the (4, 4) column-vector world_from_camera row by
row, the film (tenths of a scene unit), clipping range, image size in pixels, kind (`PRIMARY` or
`SECONDARY`) and group (the cube of a primary camera's six faces; the camera itself otherwise)."""
PRIMARY, SECONDARY = 0, 1
_COLUMN = {name: i for i, name in enumerate(CAMERA_COLUMNS)}


def camera_column(table: np.ndarray, name: str) -> np.ndarray:
    """(K,) column `name` of a (K, C) camera table."""
    return table[:, _COLUMN[name]]


def world_from_camera(table: np.ndarray) -> np.ndarray:
    """(K, 4, 4) float64 world_from_camera of a (K, C) camera table."""
    return np.asarray(table[:, :16], np.float64).reshape(-1, 4, 4)


def camera_forward(table: np.ndarray) -> np.ndarray:
    """(K, 3) float64 unit world viewing direction (camera -Z) of each camera of a (K, C) table."""
    forward = -world_from_camera(table)[:, :3, 2]
    return forward / np.linalg.norm(forward, axis=-1, keepdims=True)


def check_camera_table(table: np.ndarray, source: str) -> None:
    """Raise ValueError unless `table` is a finite (K, C) camera table with positive image sizes."""
    if table.ndim != 2 or table.shape[1] != len(CAMERA_COLUMNS):
        raise ValueError(f"{source}: camera table must be (K, {len(CAMERA_COLUMNS)}), got {table.shape}")
    if not np.all(np.isfinite(table)):
        raise ValueError(f"{source}: camera table has non-finite values")
    size = table[:, [_COLUMN["width"], _COLUMN["height"]]]
    if np.any(size < 1) or np.any(size != np.round(size)):
        raise ValueError(f"{source}: camera image sizes must be positive integers")
    film = table[:, [_COLUMN["focalLength"], _COLUMN["horizontalAperture"], _COLUMN["verticalAperture"]]]
    if np.any(film <= 0):
        raise ValueError(f"{source}: focal lengths and apertures must be > 0")


BLEND_FIELDS = tuple(f.name for f in dataclasses.fields(PreviewSurfaceParams) if f.name != "use_specular_workflow")
"""What bilinear resampling blends into the material: the floating material parameters, in
`PreviewSurfaceParams` field order (the shading normal is blended apart, where it is kept)."""


def _blend_sources(gbuffer: GBuffer) -> list[torch.Tensor]:
    return [getattr(gbuffer.params, name) for name in BLEND_FIELDS]


def pack_blend_table(gbuffer: GBuffer) -> torch.Tensor:
    """(N, C) float32 of `BLEND_FIELDS` side by side."""
    return torch.cat([t.float().reshape(t.shape[0], -1) for t in _blend_sources(gbuffer)], -1)


def unpack_blend_columns(columns: list[torch.Tensor], like: GBuffer) -> dict[str, torch.Tensor]:
    """`BLEND_FIELDS` name -> values from the C packed columns, (N,) each, shaped and typed as
    `like`'s fields."""
    out, start = {}, 0
    for name, source in zip(BLEND_FIELDS, _blend_sources(like), strict=True):
        width = source[0].numel() if source.dim() > 1 else 1
        values = torch.stack(columns[start : start + width], -1) if source.dim() > 1 else columns[start]
        out[name] = values.to(source.dtype)
        start += width
    return out


SAME_SURFACE_COS = 0.7
"""Two samples are of the same surface when of the same object with geometric normals within this
cosine (the correspondence map's test, and which caching pixels resampling blends)."""

NEIGHBOURS = tuple((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0))
"""(drow, dcol) of a pixel's eight neighbours, in the order of `CachingViews.neighbours`."""


def neighbour_slot(drow: torch.Tensor, dcol: torch.Tensor) -> torch.Tensor:
    """Index into `NEIGHBOURS` of the offsets (drow, dcol) (...) int64, not both 0."""
    slot = (drow + 1) * 3 + dcol + 1
    return slot - (slot > 4).long()


def same_object_neighbours(
    image: torch.Tensor, size: tuple[int, int], pixel: torch.Tensor, rows: torch.Tensor, object_id: torch.Tensor
) -> torch.Tensor:
    """(8, n) int32 the pool rows at each `NEIGHBOURS` offset of n samples of one view, -1 where
    outside the image, empty or another object than the sample's.

    Args:
        image: (H W,) int64 pool row of each of the view's pixels (-1: empty); size: (H, W).
        pixel: (n,) int64 flat pixel of each sample; rows: (n,) int64 its pool row.
        object_id: (R,) the pool's objects.
    """
    height, width = size
    line, column = pixel // width, pixel % width
    out = []
    for dy, dx in NEIGHBOURS:
        y, x = line + dy, column + dx
        inside = (y >= 0) & (y < height) & (x >= 0) & (x < width)
        other = torch.where(inside, image[(y.clamp(0, height - 1) * width + x.clamp(0, width - 1))], -1)
        same = (other >= 0) & (object_id[other.clamp(min=0)] == object_id[rows])
        out.append(torch.where(same, other, -1))
    return torch.stack(out).to(torch.int32)


CONSTANT, PER_MATERIAL, TEXTURED = 0, 1, 2
"""Kinds of packed material columns (`CachingViews.blend_kind`): the same over the whole pool, the
same within each material, or varying within a material (textures: what resampling blends)."""


def column_kinds(packed: torch.Tensor, material_id: torch.Tensor) -> torch.Tensor:
    """(C,) int64 kind of each column of an (R, C) packed table over samples of `material_id` (R,)."""
    if packed.shape[0] == 0:
        return torch.zeros(packed.shape[1], dtype=torch.int64, device=packed.device)
    index = material_id.long()[:, None].expand_as(packed)
    size = (int(material_id.max()) + 1, packed.shape[1])
    low = packed.new_full(size, torch.inf).scatter_reduce(0, index, packed, "amin")
    high = packed.new_full(size, -torch.inf).scatter_reduce(0, index, packed, "amax")
    textured = (high > low).any(0)
    varying = (packed != packed[:1]).any(0)
    return torch.where(textured, TEXTURED, torch.where(varying, PER_MATERIAL, CONSTANT))


def cube_faces(table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((C, 6) int64 camera of each face of each cube, -1 where dropped; (S,) int64 the other cameras)
    of a (K, C) camera table.

    A cube is the PRIMARY cameras of one group at one centre, each a square, centred 90-degree view
    down a world axis, no two down the same one: face 2 axis + (negative) (+x, -x, +y, -y, +z, -z,
    as the baker places them). Its six frusta tile the sphere of directions, so a point lies in the
    face of the largest component of its direction from the centre. Anything else is single.
    """
    world, forward = world_from_camera(table), camera_forward(table)
    axis = np.abs(forward).argmax(-1)
    face = 2 * axis + (forward[np.arange(len(table)), axis] < 0)
    focal = camera_column(table, "focalLength")
    square = (
        np.isclose(camera_column(table, "horizontalAperture"), 2.0 * focal)
        & np.isclose(camera_column(table, "verticalAperture"), 2.0 * focal)
        & (camera_column(table, "horizontalApertureOffset") == 0)
        & (camera_column(table, "verticalApertureOffset") == 0)
        & (camera_column(table, "width") == camera_column(table, "height"))
        & np.isclose(np.abs(forward).max(-1), 1.0)
    )
    candidates = (camera_column(table, "kind") == PRIMARY) & square
    groups: dict[int, list[int]] = {}
    for k in map(int, np.flatnonzero(candidates)):
        groups.setdefault(int(camera_column(table, "group")[k]), []).append(k)
    cubes, singles = [], [int(k) for k in np.flatnonzero(~candidates)]
    for members in groups.values():
        centre = world[members[0], :3, 3]
        if len({int(face[k]) for k in members}) < len(members) or not all(
            np.allclose(world[k, :3, 3], centre) for k in members
        ):
            singles += members
            continue
        faces = [-1] * 6
        for k in members:
            faces[int(face[k])] = k
        cubes.append(faces)
    return np.array(cubes, np.int64).reshape(-1, 6), np.array(sorted(singles), np.int64)


def take_rows(columns: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """(C, ...) the columns (C, R) at `rows` (...) int64: one `index_select` per call, on the CPU
    much faster than advanced indexing (`columns[:, rows]`) or a gather of (R, C) rows."""
    return columns.index_select(1, rows.reshape(-1)).reshape(columns.shape[0], *rows.shape)


def take_small(columns: torch.Tensor, rows: torch.Tensor) -> list[torch.Tensor]:
    """The columns (C, K) of a small per-camera table at `rows` (N,): C contiguous (N,) tensors, one
    one-dimensional `index_select` each (a gather of whole rows, then a transpose, costs ~10x more)."""
    return [column.index_select(0, rows) for column in columns]


def _concat_params(parts: list[PreviewSurfaceParams]) -> PreviewSurfaceParams:
    names = [f.name for f in dataclasses.fields(PreviewSurfaceParams)]
    return PreviewSurfaceParams(**{name: torch.cat([getattr(p, name) for p in parts]) for name in names})


def concat_gbuffers(
    parts: list[GBuffer], image_size: tuple[int, int], pixel_index: torch.Tensor, camera_position: torch.Tensor
) -> GBuffer:
    """The samples of several G-buffers as one G-buffer of `image_size` at `pixel_index` (N,)."""
    tensors = {
        name: torch.cat([getattr(p, name) for p in parts])
        for name in (
            "position",
            "normal",
            "tangent",
            "bitangent",
            "geometric_normal",
            "material_id",
            "object_id",
            "depth",
        )
    }
    return GBuffer(
        image_size=image_size,
        pixel_index=pixel_index,
        params=_concat_params([p.params for p in parts]),
        camera_position=camera_position,
        **tensors,
    )


def gather_gbuffer(pool: GBuffer, rows: torch.Tensor) -> GBuffer:
    """The pool's samples at `rows` (N,), as a GBuffer with the pool's (meaningless) image fields."""
    return dataclasses.replace(
        pool,
        pixel_index=pool.pixel_index[rows],
        position=pool.position[rows],
        normal=pool.normal[rows],
        tangent=pool.tangent[rows],
        bitangent=pool.bitangent[rows],
        geometric_normal=pool.geometric_normal[rows],
        params=pool.params.index(rows),
        material_id=pool.material_id[rows],
        object_id=pool.object_id[rows],
        depth=pool.depth[rows],
    )


@dataclass(frozen=True)
class CachingViews:
    """K caching cameras with their deep framebuffers pooled (see the module docstring).

    Attributes:
        table: (K, C) float64 camera table (`CAMERA_COLUMNS`), on the CPU.
        pool: every view's covered samples, concatenated: R rows, as a (1, R) image (the image
            fields and camera_position mean nothing; the views' own are in the table).
        camera_from_world: (K, 4, 4) float64 tensor.
        sizes: (K, 2) int64 sub-sample image (height, width) of each view.
        image_offsets: (K + 1,) int64 start of each view's flat image in `pool_row` and `depth`.
        pool_row: (sum H W,) int64 pool row of each view pixel, -1 where the view hit nothing.
        depth: (sum H W,) float32 cached depth along each view's axis, inf where it hit nothing.
        pixel_angle: (K,) float32 angle one sub-sample pixel subtends at the image centre (radians).
        pool_view: (R,) int64 the view of each pool row.
        pool_pixel: (R, 2) float32 (column, row) centre of each pool row's pixel in its view.
        blend_kind: (C,) int64 kind of each of the C packed material columns (`BLEND_FIELDS`,
            `column_kinds`): constant columns (no emission, no clearcoat) cost nothing, those
            constant within each material are read from the nearest sample, and only textured
            ones are blended.
        blend_table: (V, R) the V `TEXTURED` columns, column by column (`take_rows`: one gather
            along the rows, several times faster on the CPU than a gather of (R, V) rows).
        material_table: (U, R) the U `PER_MATERIAL` columns, likewise.
        blend_constants: (C,) float32 the packed columns' values where constant.
        normal_table: (3, R) float32 shading normal of each row, column by column.
        neighbours: (8, R) int32 per row the pool rows of its eight neighbouring pixels in its
            view (`NEIGHBOURS` order), -1 where there is none of the same object
            (`same_object_neighbours`): the taps resampling may blend.
        surface_table: (4, R) float32 object id (exact below 2^24) and geometric normal of each
            row, column by column: what the same-surface tests read.
        projection: (19, K) float32, per camera what `project` reads: camera_from_world's top three
            rows (12), focal length, horizontal and vertical aperture and offset, width, height,
            so that the correspondence map projects every point into its own camera (`take_small`).
        centres: (3, K) float32 camera positions.
        cubes: (C, 6) int64 the camera of each face of each omni-directional camera (`cube_faces`:
            +x, -x, +y, -y, +z, -z), -1 where the face was dropped; singles: (S,) int64 the other
            cameras. The correspondence map scores a cube once, through the face a point lies in.
        axes: (4, K) float32 per camera its unit viewing direction (3) and the cosine of the
            half-angle of a cone around it holding its whole frustum (1% wider): a point outside
            that cone is outside the image, which the correspondence map tests before anything else.
    """

    table: np.ndarray
    pool: GBuffer
    camera_from_world: torch.Tensor
    sizes: torch.Tensor
    image_offsets: torch.Tensor
    pool_row: torch.Tensor
    depth: torch.Tensor
    pixel_angle: torch.Tensor
    pool_view: torch.Tensor
    pool_pixel: torch.Tensor
    blend_kind: torch.Tensor
    blend_table: torch.Tensor
    material_table: torch.Tensor
    blend_constants: torch.Tensor
    normal_table: torch.Tensor
    neighbours: torch.Tensor
    surface_table: torch.Tensor
    centres: torch.Tensor
    projection: torch.Tensor
    cubes: torch.Tensor
    singles: torch.Tensor
    axes: torch.Tensor

    @property
    def num_views(self) -> int:
        return int(self.table.shape[0])

    @property
    def device(self) -> torch.device:
        return self.pool.device

    @staticmethod
    def build(table: np.ndarray, gbuffers: list[GBuffer]) -> CachingViews:
        """Pool K views (`gbuffers[k]` baked by camera row k; all on one device).

        Raises:
            ValueError: the table is malformed or disagrees with the G-buffers.
        """
        check_camera_table(table, "caching views")
        if len(gbuffers) != table.shape[0]:
            raise ValueError(f"{table.shape[0]} cameras but {len(gbuffers)} deep framebuffers")
        device = gbuffers[0].device if gbuffers else torch.device("cpu")
        sizes, rows, depths, centres = [], [], [], []
        owners: list[torch.Tensor] = []
        start = 0
        for gbuffer in gbuffers:
            height, width = gbuffer.image_size
            sizes.append((height, width))
            row = torch.full((height * width,), -1, dtype=torch.int64, device=device)
            row[gbuffer.pixel_index] = torch.arange(start, start + gbuffer.num_samples, device=device)
            depth = torch.full((height * width,), torch.inf, dtype=torch.float32, device=device)
            depth[gbuffer.pixel_index] = gbuffer.depth.float()
            rows.append(row)
            depths.append(depth)
            owners.append(torch.full((gbuffer.num_samples,), len(owners), dtype=torch.int64, device=device))
            centres.append(torch.stack([gbuffer.pixel_index % width, gbuffer.pixel_index // width], -1).float() + 0.5)
            start += gbuffer.num_samples
        size_tensor = torch.tensor(sizes, dtype=torch.int64, device=device).reshape(-1, 2)
        offsets = torch.zeros(len(gbuffers) + 1, dtype=torch.int64, device=device)
        offsets[1:] = torch.cumsum(size_tensor[:, 0] * size_tensor[:, 1], 0)
        focal = camera_column(table, "focalLength")
        aperture = camera_column(table, "horizontalAperture")
        pixel_angle = aperture / focal / np.maximum(size_tensor[:, 1].cpu().numpy(), 1)
        rows_all = torch.arange(start, device=device)
        pool = concat_gbuffers(gbuffers, (1, start), rows_all, torch.zeros(3, device=device))
        neighbours = [
            same_object_neighbours(
                row, size, g.pixel_index, torch.arange(offset, offset + g.num_samples, device=device), pool.object_id
            )
            for row, size, g, offset in zip(
                rows, sizes, gbuffers, np.cumsum([0] + [g.num_samples for g in gbuffers]).tolist()[:-1], strict=True
            )
        ]
        packed = pack_blend_table(pool)
        kind = column_kinds(packed, pool.material_id)
        camera_from_world = np.linalg.inv(world_from_camera(table))
        film = np.stack(
            [
                camera_column(table, name)
                for name in (
                    "focalLength",
                    "horizontalAperture",
                    "verticalAperture",
                    "horizontalApertureOffset",
                    "verticalApertureOffset",
                )
            ],
            -1,
        )
        projection = np.concatenate(
            [camera_from_world[:, :3, :].reshape(-1, 12), film, size_tensor.cpu().numpy()[:, ::-1]], -1
        )
        forward = camera_forward(table)
        corner = np.hypot(film[:, 1] / 2 + np.abs(film[:, 3]), film[:, 2] / 2 + np.abs(film[:, 4])) / film[:, 0]
        cone = 1.0 / np.sqrt(1.0 + (1.01 * corner) ** 2)
        cubes, singles = cube_faces(table)
        return CachingViews(
            table=np.asarray(table, np.float64),
            pool=pool,
            camera_from_world=torch.from_numpy(camera_from_world).to(device),
            sizes=size_tensor,
            image_offsets=offsets,
            pool_row=torch.cat(rows),
            depth=torch.cat(depths),
            pixel_angle=torch.as_tensor(pixel_angle, dtype=torch.float32, device=device),
            pool_view=torch.cat(owners) if owners else torch.zeros(0, dtype=torch.int64, device=device),
            pool_pixel=torch.cat(centres) if centres else torch.zeros((0, 2), device=device),
            blend_kind=kind,
            blend_table=packed[:, kind == TEXTURED].T.contiguous(),
            material_table=packed[:, kind == PER_MATERIAL].T.contiguous(),
            blend_constants=packed[0] if start else packed.new_zeros(packed.shape[1]),
            normal_table=pool.normal.float().T.contiguous(),
            neighbours=torch.cat(neighbours, 1) if neighbours else torch.zeros((8, 0), dtype=torch.int32),
            surface_table=torch.cat([pool.object_id.float()[None], pool.geometric_normal.float().T]),
            centres=torch.as_tensor(
                world_from_camera(table)[:, :3, 3].T.copy(), dtype=torch.float32, device=device
            ).reshape(3, -1),
            projection=torch.as_tensor(projection, dtype=torch.float32, device=device).reshape(-1, 19).T.contiguous(),
            cubes=torch.as_tensor(cubes, dtype=torch.int64, device=device).reshape(-1, 6),
            singles=torch.as_tensor(singles, dtype=torch.int64, device=device).reshape(-1),
            axes=torch.as_tensor(
                np.concatenate([forward, cone[:, None]], -1).T.copy(), dtype=torch.float32, device=device
            ).reshape(4, -1),
        )

    def camera_position(self, k: int) -> torch.Tensor:
        """(3,) float32 world position of camera k."""
        position = world_from_camera(self.table[k : k + 1])[0, :3, 3]
        return torch.as_tensor(position, dtype=torch.float32, device=self.device)

    def project(self, k: int, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Points (N, 3) into camera k's sub-sample image.

        Returns:
            pixels (N, 2) float32 continuous (column, row) coordinates, NaN behind the camera;
            depth (N,) float32 distance along the view axis (<= 0 behind).
        """
        matrix = self.camera_from_world[k].to(points.dtype)
        local = points @ matrix[:3, :3].T + matrix[:3, 3]
        depth = -local[:, 2]
        row = self.table[k]
        focal = float(row[_COLUMN["focalLength"]])
        safe = torch.where(depth > 0, depth, torch.ones_like(depth))
        x_film = focal * local[:, 0] / safe
        y_film = focal * local[:, 1] / safe
        height, width = (int(v) for v in self.sizes[k])
        column = (
            (x_film - float(row[_COLUMN["horizontalApertureOffset"]])) / float(row[_COLUMN["horizontalAperture"]]) + 0.5
        ) * width
        line = (
            0.5 - (y_film - float(row[_COLUMN["verticalApertureOffset"]])) / float(row[_COLUMN["verticalAperture"]])
        ) * height
        pixels = torch.stack((column, line), -1)
        pixels = torch.where((depth > 0)[:, None], pixels, torch.full_like(pixels, torch.nan))
        return pixels, depth
