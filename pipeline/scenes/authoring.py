"""USD authoring helpers shared by the bundled scenes: stage, transforms, meshes, materials, camera.

Conventions of every bundled stage: an in-memory stage with `defaultPrim` /World, `upAxis` Y and
`metersPerUnit` set, exported atomically to DIR/<name>.usda; lights and cameras placed with
`xformOp:translate` + `xformOp:rotateXYZ` so light-edit layers can override either op alone;
UsdPreviewSurface materials under /World/Materials, bound with MaterialBindingAPI applied; a
UsdRender.Settings prim at /Render/Settings naming the camera and the resolution.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender, UsdShade, Vt

from pipeline.scenes.meshes import MeshData
from relight_torch.io.atomic import atomic_path
from relight_torch.schema import register_schemas

WORLD = "/World"
MATERIALS = "/World/Materials"
GEOMETRY = "/World/Geometry"
LIGHTS = "/World/Lights"
RENDER_SETTINGS = "/Render/Settings"

# Sdf types of the UsdPreviewSurface inputs we author (26.11 Sdr node, USD_EXR_NOTES section 2).
_PREVIEW_INPUT_TYPES = {
    "diffuseColor": Sdf.ValueTypeNames.Color3f,
    "emissiveColor": Sdf.ValueTypeNames.Color3f,
    "useSpecularWorkflow": Sdf.ValueTypeNames.Int,
    "specularColor": Sdf.ValueTypeNames.Color3f,
    "metallic": Sdf.ValueTypeNames.Float,
    "roughness": Sdf.ValueTypeNames.Float,
    "clearcoat": Sdf.ValueTypeNames.Float,
    "clearcoatRoughness": Sdf.ValueTypeNames.Float,
    "opacity": Sdf.ValueTypeNames.Float,
    "opacityThreshold": Sdf.ValueTypeNames.Float,
    "ior": Sdf.ValueTypeNames.Float,
    "normal": Sdf.ValueTypeNames.Normal3f,
}


def create_stage(meters_per_unit: float, doc: str) -> Usd.Stage:
    """An in-memory stage: /World (default prim) with Materials (Scope), Geometry and Lights (Xforms)."""
    register_schemas()  # before any stage exists in this process (USD_EXR_NOTES 4)
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    stage.GetRootLayer().documentation = doc
    world = UsdGeom.Xform.Define(stage, WORLD)
    stage.SetDefaultPrim(world.GetPrim())
    UsdGeom.Scope.Define(stage, MATERIALS)
    UsdGeom.Xform.Define(stage, GEOMETRY)
    UsdGeom.Xform.Define(stage, LIGHTS)
    return stage


def save_stage(stage: Usd.Stage, path: Path) -> Path:
    """Export the stage's root layer to `path` atomically (temp file, then rename); returns `path`."""
    with atomic_path(path) as temp:
        if not stage.GetRootLayer().Export(str(temp)):
            raise OSError(f"could not write USD layer {temp}")
    return path


def aim_rotation_xyz(direction: np.ndarray) -> Gf.Vec3f:
    """Euler angles (degrees, `xformOp:rotateXYZ`) turning local -Z onto `direction`, without roll.

    rotateXYZ applies X first, then Y: local -Z -> (0, sin a, -cos a) -> (-sin b cos a, sin a,
    -cos b cos a), so a = asin(d_y), b = atan2(-d_x, -d_z) (b = 0 straight up or down). Local +X
    stays horizontal, so a camera aimed this way keeps +Y up.

    Args:
        direction: (3,) direction to aim at, any length > 0.
    """
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    pitch = np.degrees(np.arcsin(np.clip(d[1], -1.0, 1.0)))
    yaw = np.degrees(np.arctan2(-d[0], -d[2])) if np.hypot(d[0], d[2]) > 1e-9 else 0.0
    return Gf.Vec3f(float(pitch), float(yaw), 0.0)


def place(xformable: UsdGeom.Xformable, translate, rotate_xyz=None, scale=None) -> None:
    """Author xformOp:translate, then optionally xformOp:rotateXYZ (degrees) and xformOp:scale."""
    xformable.AddTranslateOp().Set(Gf.Vec3d(*map(float, translate)))
    if rotate_xyz is not None:
        xformable.AddRotateXYZOp().Set(Gf.Vec3f(*map(float, rotate_xyz)))
    if scale is not None:
        xformable.AddScaleOp().Set(Gf.Vec3f(*map(float, scale)))


def place_aimed(xformable: UsdGeom.Xformable, position, target) -> None:
    """Place a light or camera at `position` with its local -Z pointing at `target`."""
    direction = np.asarray(target, np.float64) - np.asarray(position, np.float64)
    place(xformable, position, aim_rotation_xyz(direction))


def define_mesh(stage: Usd.Stage, path: str, mesh: MeshData) -> UsdGeom.Mesh:
    """A polygonal (subdivisionScheme none) right-handed mesh with extent, normals and st primvars."""
    usd_mesh = UsdGeom.Mesh.Define(stage, path)
    usd_mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    usd_mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(mesh.points))
    usd_mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(mesh.face_vertex_counts))
    usd_mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(mesh.face_vertex_indices))
    usd_mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([mesh.points.min(axis=0), mesh.points.max(axis=0)])))
    primvars = UsdGeom.PrimvarsAPI(usd_mesh)
    if mesh.normals is not None:
        primvars.CreatePrimvar("normals", Sdf.ValueTypeNames.Normal3fArray, UsdGeom.Tokens.vertex).Set(
            Vt.Vec3fArray.FromNumpy(mesh.normals)
        )
    if mesh.st is not None:
        primvars.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
            Vt.Vec2fArray.FromNumpy(mesh.st)
        )
    return usd_mesh


def define_preview_material(stage: Usd.Stage, name: str, **inputs) -> tuple[UsdShade.Material, UsdShade.Shader]:
    """A Material /World/Materials/<name> whose surface is a UsdPreviewSurface with constant `inputs`.

    Args:
        name: material prim name.
        **inputs: UsdPreviewSurface input names (e.g. diffuseColor=(r, g, b), roughness=0.4).
    """
    material = UsdShade.Material.Define(stage, f"{MATERIALS}/{name}")
    shader = UsdShade.Shader.Define(stage, f"{MATERIALS}/{name}/PreviewSurface")
    shader.CreateIdAttr("UsdPreviewSurface")
    for input_name, value in inputs.items():
        value_type = _PREVIEW_INPUT_TYPES[input_name]
        if value_type in (Sdf.ValueTypeNames.Color3f, Sdf.ValueTypeNames.Normal3f):
            value = Gf.Vec3f(*map(float, value))
        shader.CreateInput(input_name, value_type).Set(value)
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    return material, shader


def connect_texture(
    material: UsdShade.Material,
    shader: UsdShade.Shader,
    input_name: str,
    file: str,
    *,
    source_color_space: str,
    scale=None,
    bias=None,
    output: str = "rgb",
) -> UsdShade.Shader:
    """Feed a UsdPreviewSurface input from an image through UsdUVTexture, reading primvar 'st'.

    Args:
        input_name: 'diffuseColor' (rgb output) or 'normal' (rgb output, normal3f input), etc.
        file: asset path relative to the layer, e.g. './textures/glossy_brick_albedo.png'.
        source_color_space: 'sRGB' for colour images, 'raw' for data (normal maps).
        scale, bias: (4,) float4 applied as out = texel * scale + bias, or None for the fallbacks.
        output: the texture output connected: 'rgb' (float3) or one channel 'r', 'g', 'b', 'a' (float).
    """
    stage = material.GetPrim().GetStage()
    material_path = material.GetPath()
    reader_path = material_path.AppendChild("StReader")
    reader = UsdShade.Shader.Get(stage, reader_path)
    if not reader:
        reader = UsdShade.Shader.Define(stage, reader_path)
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")  # string, not token
        reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    texture = UsdShade.Shader.Define(stage, material_path.AppendChild(f"{input_name}Texture"))
    texture.CreateIdAttr("UsdUVTexture")
    texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(file))
    texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
    texture.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("repeat")
    texture.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("repeat")
    texture.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(source_color_space)
    if scale is not None:
        texture.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*map(float, scale)))
    if bias is not None:
        texture.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*map(float, bias)))
    texture.CreateOutput(output, Sdf.ValueTypeNames.Float3 if output == "rgb" else Sdf.ValueTypeNames.Float)
    input_type = _PREVIEW_INPUT_TYPES[input_name]
    shader.CreateInput(input_name, input_type).ConnectToSource(texture.ConnectableAPI(), output)
    return texture


def bind_material(prim: Usd.Prim, material: UsdShade.Material) -> None:
    """Bind with MaterialBindingAPI applied first (an unapplied binding is a validation error)."""
    UsdShade.MaterialBindingAPI.Apply(prim).Bind(material)


def define_camera(
    stage: Usd.Stage,
    path: str,
    position,
    target,
    *,
    focal_length_mm: float,
    aperture_mm: tuple[float, float],
    clipping_range: tuple[float, float],
) -> UsdGeom.Camera:
    """A perspective camera at `position` looking at `target` with +Y up.

    USD stores focal length and apertures in tenths of a scene unit: 35 mm is 35 when
    metersPerUnit = 0.01 but 350 when metersPerUnit = 0.001. Only their ratio sets the field of view.

    Args:
        focal_length_mm: physical focal length in millimetres.
        aperture_mm: (horizontal, vertical) film size in millimetres.
        clipping_range: (near, far) in scene units.
    """
    tenths_per_mm = 1e-3 / (0.1 * UsdGeom.GetStageMetersPerUnit(stage))
    camera = UsdGeom.Camera.Define(stage, path)
    place_aimed(camera, position, target)
    camera.CreateProjectionAttr(UsdGeom.Tokens.perspective)
    camera.CreateFocalLengthAttr(focal_length_mm * tenths_per_mm)
    camera.CreateHorizontalApertureAttr(aperture_mm[0] * tenths_per_mm)
    camera.CreateVerticalApertureAttr(aperture_mm[1] * tenths_per_mm)
    camera.CreateClippingRangeAttr(Gf.Vec2f(*clipping_range))
    return camera


def define_render_settings(stage: Usd.Stage, camera: UsdGeom.Camera, resolution: tuple[int, int]) -> None:
    """/Render/Settings (UsdRender.Settings) with the camera and (width, height), named by the stage."""
    settings = UsdRender.Settings.Define(stage, RENDER_SETTINGS)
    settings.CreateResolutionAttr(Gf.Vec2i(*resolution))
    settings.CreatePixelAspectRatioAttr(1.0)
    settings.CreateCameraRel().SetTargets([camera.GetPath()])
    stage.SetMetadata("renderSettingsPrimPath", RENDER_SETTINGS)


def set_light(light: UsdLux.LightAPI, *, intensity: float, color=(1.0, 1.0, 1.0), normalize: bool = False) -> None:
    """Author the radiometric inputs common to every light (see USD_EXR_NOTES 1.2)."""
    light.CreateIntensityAttr(float(intensity))
    light.CreateColorAttr(Gf.Vec3f(*map(float, color)))
    light.CreateNormalizeAttr(bool(normalize))


def shape_spot(prim: Usd.Prim, *, cone_angle: float, softness: float, focus: float) -> None:
    """Apply ShapingAPI: cone half-angle (degrees), softness in [0, 1], focus exponent."""
    shaping = UsdLux.ShapingAPI.Apply(prim)
    shaping.CreateShapingConeAngleAttr(float(cone_angle))
    shaping.CreateShapingConeSoftnessAttr(float(softness))
    shaping.CreateShapingFocusAttr(float(focus))
