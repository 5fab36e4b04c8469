"""The in-memory scene every part of the project shares.

A `Scene` is what the USD walker (`pipeline.scene.load_scene`) produces from a stage and what the
tracer, the bakers and the reference renderer consume: world-space triangle soup with per-corner
shading attributes, materials with their (unevaluated) textures, lights and cameras.

Conventions:
    * Matrices are float64 (4, 4) in column-vector form, named `a_from_b`:
      p_a = a_from_b[:3, :3] @ p_b + a_from_b[:3, 3]. (USD's Gf matrices are row-vector; the walker
      transposes them once, at read time.)
    * Lengths are in scene units; `Scene.meters_per_unit` says what a unit is.
    * Colours are linear Rec.709 RGB.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from relight_torch.lights.light import Light


@dataclass(frozen=True)
class Texture:
    """A `UsdUVTexture` node, decoded to linear float pixels.

    Attributes:
        file: resolved path of the image file.
        pixels: (H, W, C) float32, linear (sRGB decoded where `sourceColorSpace` asks for it);
            row 0 is the TOP of the image (numpy order), so st=(0, 0) is pixels[H - 1, 0].
        wrap_s, wrap_t: 'black', 'clamp', 'repeat' or 'mirror'.
        scale, bias: (4,) float32; output = sample * scale + bias (RGBA; missing channels as
            UsdUVTexture fills them: G=B=R for one channel, A=1).
        fallback: (4,) float32, returned outside the image when wrap is 'black' is NOT it (black is 0);
            used when the file could not be read.
        output: which output is connected: 'rgb', 'r', 'g', 'b' or 'a'.
        st_primvar: name of the primvar the st input reads (from UsdPrimvarReader_float2), e.g. 'st'.
        st_from_uv: (3, 3) float64 affine transform from the primvar to the texture's st
            (UsdTransform2d), identity if none.
    """

    file: str
    pixels: np.ndarray
    wrap_s: str = "repeat"
    wrap_t: str = "repeat"
    scale: np.ndarray = field(default_factory=lambda: np.ones(4, np.float32))
    bias: np.ndarray = field(default_factory=lambda: np.zeros(4, np.float32))
    fallback: np.ndarray = field(default_factory=lambda: np.array([0, 0, 0, 1], np.float32))
    output: str = "rgb"
    st_primvar: str = "st"
    st_from_uv: np.ndarray = field(default_factory=lambda: np.eye(3))


@dataclass(frozen=True)
class MaterialInput:
    """One UsdPreviewSurface input: a constant, optionally replaced by a texture lookup.

    Attributes:
        value: (C,) float32 constant (C = 3 for colours and normals, 1 for scalars); the value used
            where there is no texture or the texture could not be read.
        texture: the connected texture, or None.
    """

    value: np.ndarray
    texture: Texture | None = None


def _const(*values: float) -> MaterialInput:
    return MaterialInput(np.asarray(values, np.float32))


@dataclass(frozen=True)
class Material:
    """A UsdPreviewSurface material (spec 2.5 + the 26.11 Sdr node), inputs unevaluated.

    Fallbacks are the 26.11 registered defaults. `path` is the material prim's path, or
    '<displayColor>' / '<fallback>' for materials the walker synthesised. `documents` are the
    files outside USD the material was read from (MaterialX `.mtlx` documents): bake inputs.
    """

    path: str
    diffuse_color: MaterialInput = field(default_factory=lambda: _const(0.18, 0.18, 0.18))
    emissive_color: MaterialInput = field(default_factory=lambda: _const(0.0, 0.0, 0.0))
    use_specular_workflow: bool = False
    specular_color: MaterialInput = field(default_factory=lambda: _const(0.0, 0.0, 0.0))
    metallic: MaterialInput = field(default_factory=lambda: _const(0.0))
    roughness: MaterialInput = field(default_factory=lambda: _const(0.5))
    clearcoat: MaterialInput = field(default_factory=lambda: _const(0.0))
    clearcoat_roughness: MaterialInput = field(default_factory=lambda: _const(0.01))
    opacity: MaterialInput = field(default_factory=lambda: _const(1.0))
    opacity_threshold: float = 0.0
    opacity_mode: str = "transparent"
    ior: MaterialInput = field(default_factory=lambda: _const(1.5))
    normal: MaterialInput = field(default_factory=lambda: _const(0.0, 0.0, 1.0))
    documents: tuple[str, ...] = ()

    def replace(self, **changes) -> Material:
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class Geometry:
    """All renderable surfaces of the stage as one world-space triangle soup.

    T triangles, each with its own three corners (no shared vertices), so face-varying primvars
    need no special case.

    Attributes:
        positions: (T, 3, 3) float32 world-space corner positions [triangle, corner, xyz].
        normals: (T, 3, 3) float32 unit shading normals per corner (authored, else smooth for
            subdivision meshes, else the face normal), oriented to agree with the winding.
        uvs: (T, 3, 2) float32 'st' primvar per corner (zeros where the mesh has none).
        material_ids: (T,) int32 index into `Scene.materials`.
        object_ids: (T,) int32 index into `Scene.objects`.
    """

    positions: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray
    material_ids: np.ndarray
    object_ids: np.ndarray

    @property
    def num_triangles(self) -> int:
        return int(self.positions.shape[0])


@dataclass(frozen=True)
class SceneObject:
    """One gprim instance as it appears in the soup.

    Attributes:
        path: the prim path (for instances, the instance proxy or '<instancer>[i]/<proto path>').
        double_sided: the gprim's `doubleSided`.
    """

    path: str
    double_sided: bool


@dataclass(frozen=True)
class Camera:
    """A `UsdGeom.Camera` at one time code, with the image size it is rendered at.

    Attributes:
        path: camera prim path.
        world_from_camera: (4, 4) float64; the camera looks down its local -Z with +Y up.
        focal_length, horizontal_aperture, vertical_aperture,
        horizontal_aperture_offset, vertical_aperture_offset: in scene units / 10 (USD's
            "tenths of a scene unit"), as authored. Only their ratios matter for a pinhole.
        clipping_range: (near, far) in scene units.
        width, height: image size in pixels.
        exposure_scale: `UsdGeom.Camera.ComputeLinearExposureScale()`, applied to rendered radiance.
    """

    path: str
    world_from_camera: np.ndarray
    focal_length: float
    horizontal_aperture: float
    vertical_aperture: float
    horizontal_aperture_offset: float
    vertical_aperture_offset: float
    clipping_range: tuple[float, float]
    width: int
    height: int
    exposure_scale: float = 1.0


@dataclass(frozen=True)
class Scene:
    """Everything the bakers, tracer and reference renderer need from a stage.

    Attributes:
        source: path of the stage's root layer.
        geometry: the triangle soup.
        objects: per object id.
        materials: per material id.
        lights: every UsdLux light.
        cameras: every camera prim, keyed by path.
        meters_per_unit: stage metadata.
        up_axis: 'Y' or 'Z'.
        warnings: the one-line warnings the walker emitted (also logged).
        read_size: the (width, height) image size overrides the stage was read with (`load_scene`;
            None: the stage's own): its subdivision surfaces are refined for its cameras at that
            size (`pipeline.scene.dicing`), whatever size a camera of it is later set to.
    """

    source: str
    geometry: Geometry
    objects: list[SceneObject]
    materials: list[Material]
    lights: list[Light]
    cameras: dict[str, Camera]
    meters_per_unit: float = 0.01
    up_axis: str = "Y"
    warnings: list[str] = field(default_factory=list)
    read_size: tuple[int | None, int | None] = (None, None)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min (3,), max (3,)) float64 world bounds of the geometry."""
        p = self.geometry.positions.reshape(-1, 3)
        return p.min(axis=0).astype(np.float64), p.max(axis=0).astype(np.float64)

    @property
    def diagonal(self) -> float:
        """Length of the bounding-box diagonal; ray epsilons and tolerances scale with it."""
        lo, hi = self.bounds
        return float(np.linalg.norm(hi - lo))
