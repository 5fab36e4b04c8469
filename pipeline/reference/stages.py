"""Small shots under environment light, authored for the reference's own checks.

One stage layout, varied by `ShotSpec`: a grey floor, a constant-diffuse ball with authored
normals, a glossy ball without authored normals (catmullClark, smooth normals computed by the
loader, as a subdivision asset arrives) and a glossy metal block, under one of:

    constant   a DomeLight of radiance 0.5, no texture
    latlong    a DomeLight with a lat-long EXR (a sky gradient, a dim ground and a small sun of
               radiance 200, 32 x 64 texels), rotated by its transform (rotateXYZ (10, 65, 0)), so
               that a wrong orientation, a mirrored or a shifted sky moves the sun's light
    latlong8   the same sky clipped to [0, 1] as an 8-bit sRGB PNG, intensity 0.5: a game-style sky
    sun        a DistantLight of angle 0.53 degrees and radiance 2e4, alone

The sky is written from the UsdLux lat-long convention itself (+Y pole; u = 0.5 - atan2(x, z) / 2 pi,
v_from_top = acos(y) / pi, USD_EXR_NOTES 1.2), not from `relight_torch.lights.dome`, so the stages
can check that code. `normal_map` adds an 8-bit tangent-space normal map of strong random tilts to
the floor and the glossy materials.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pxr import Gf, UsdGeom, UsdLux

from pipeline.scenes import authoring, meshes
from pipeline.scenes.textures import srgb_encode, write_png
from relight_torch.io.exr import write_rgb_exr

LIGHTINGS = ("constant", "latlong", "latlong8", "sun")
CAMERA = "/World/Camera"
DOME = "/World/Lights/Dome"
DOME_ROTATE_XYZ = (10.0, 65.0, 0.0)
"""The dome's rotation (degrees, xformOp:rotateXYZ)."""
SKY_SIZE = (32, 64)
SUN_LOCAL = np.array([0.45, 0.62, -0.643])
"""Direction of the sky's sun in the dome's frame (unnormalised; elevation ~38 degrees)."""
SUN_RADIANCE = 200.0
SUN_RADIUS_DEGREES = 7.0
CONSTANT_RADIANCE = 0.5
DISTANT_RADIANCE = 2e4
OBJECTS = (
    "/World/Geometry/Floor",
    "/World/Geometry/DiffuseBall",
    "/World/Geometry/GlossyBall",
    "/World/Geometry/GlossyBlock",
)


@dataclass(frozen=True)
class ShotSpec:
    """What varies between the shots.

    Attributes:
        lighting: one of LIGHTINGS.
        normal_map: an 8-bit normal map on the floor and the glossy materials.
        roughness: the glossy ball's and block's roughness.
        width, height: the image.
    """

    lighting: str = "constant"
    normal_map: bool = False
    roughness: float = 0.3
    width: int = 32
    height: int = 24

    @property
    def camera(self) -> str:
        return CAMERA

    def peak_radiance(self) -> float:
        """The largest radiance any light of the shot emits towards any direction."""
        if self.lighting == "constant":
            return CONSTANT_RADIANCE
        if self.lighting == "sun":
            return DISTANT_RADIANCE
        sky = sky_texture()
        return float(sky.max()) if self.lighting == "latlong" else CONSTANT_RADIANCE * float(np.clip(sky, 0, 1).max())


def usd_latlong_directions(height: int, width: int) -> np.ndarray:
    """(H, W, 3) unit directions of the texel centres in the dome's frame, from the UsdLux convention:
    u = 0.5 - atan2(x, z) / (2 pi), v_from_top = acos(y) / pi (row 0 = +Y)."""
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(width) + 0.5) / width
    theta = v[:, None] * math.pi
    longitude = (0.5 - u[None, :]) * 2.0 * math.pi
    return np.stack(
        np.broadcast_arrays(np.sin(theta) * np.sin(longitude), np.cos(theta), np.sin(theta) * np.cos(longitude)),
        axis=-1,
    )


def sky_texture(height: int = SKY_SIZE[0], width: int = SKY_SIZE[1]) -> np.ndarray:
    """(H, W, 3) float32 linear radiance: sky gradient, dim ground, a small sun (row 0 = +Y pole)."""
    direction = usd_latlong_directions(height, width)
    up = direction[..., 1:2]
    zenith, horizon = np.array([0.2, 0.35, 0.8]), np.array([0.7, 0.7, 0.72])
    sky = horizon + (zenith - horizon) * np.clip(up, 0.0, 1.0) ** 0.5
    image = np.where(up > 0, sky, np.array([0.1, 0.07, 0.05]))
    sun_direction = SUN_LOCAL / np.linalg.norm(SUN_LOCAL)
    sun_angle = np.degrees(np.arccos(np.clip(direction @ sun_direction, -1.0, 1.0)))
    image = image + (sun_angle < SUN_RADIUS_DEGREES)[..., None] * SUN_RADIANCE * np.array([1.0, 0.9, 0.75])
    return image.astype(np.float32)


def dome_world_from_light() -> np.ndarray:
    """(4, 4) the dome's transform as `xformOp:rotateXYZ DOME_ROTATE_XYZ` authors it (column vectors)."""
    rx, ry, rz = (math.radians(a) for a in DOME_ROTATE_XYZ)
    x = np.array([[1, 0, 0], [0, math.cos(rx), -math.sin(rx)], [0, math.sin(rx), math.cos(rx)]])
    y = np.array([[math.cos(ry), 0, math.sin(ry)], [0, 1, 0], [-math.sin(ry), 0, math.cos(ry)]])
    z = np.array([[math.cos(rz), -math.sin(rz), 0], [math.sin(rz), math.cos(rz), 0], [0, 0, 1]])
    matrix = np.eye(4)
    matrix[:3, :3] = z @ y @ x  # rotateXYZ: X first
    return matrix


def _normal_map(size: int = 32, tilt: float = 1.5, seed: int = 5) -> np.ndarray:
    """(size, size, 3) encoded tangent-space normals in [0, 1] with strong random tilts."""
    rng = np.random.default_rng(seed)
    normals = np.concatenate([rng.normal(0.0, tilt, (size, size, 2)), np.ones((size, size, 1))], axis=-1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return normals * 0.5 + 0.5


def write_shot(directory: Path, spec: ShotSpec) -> Path:
    """Write DIR/shot_<lighting>.usda (and its textures); return its path."""
    if spec.lighting not in LIGHTINGS:
        raise ValueError(f"lighting must be one of {LIGHTINGS}, got {spec.lighting!r}")
    directory = Path(directory)
    (directory / "textures").mkdir(parents=True, exist_ok=True)
    stage = authoring.create_stage(1.0, f"Reference check shot: {spec}.")
    floor = authoring.define_mesh(stage, OBJECTS[0], meshes.plane(8.0, 8.0, st_repeat=8.0))
    ball = authoring.define_mesh(
        stage, OBJECTS[1], meshes.transformed(meshes.uv_sphere(0.6, 24, 12), _translation(-1.0, 0.6, 0.3))
    )
    smooth = meshes.transformed(meshes.uv_sphere(0.55, 16, 8), _translation(0.45, 0.55, 0.6))
    glossy_ball = authoring.define_mesh(
        stage,
        OBJECTS[2],
        meshes.MeshData(smooth.points, smooth.face_vertex_counts, smooth.face_vertex_indices, None, smooth.st),
    )
    glossy_ball.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.catmullClark)
    block = authoring.define_mesh(stage, OBJECTS[3], meshes.box((0.9, 0.7, 0.9), (1.2, 0.35, -0.9)))
    looks = {
        "Floor": {"diffuseColor": (0.45, 0.42, 0.38), "roughness": 0.9},
        "Diffuse": {"diffuseColor": (0.8, 0.35, 0.2), "roughness": 1.0},
        "Glossy": {"diffuseColor": (0.1, 0.2, 0.6), "roughness": spec.roughness},
        "Metal": {"diffuseColor": (0.9, 0.65, 0.3), "metallic": 1.0, "roughness": spec.roughness},
    }
    normal_file = "./textures/normals.png"
    if spec.normal_map:
        write_png(directory / "textures" / "normals.png", _normal_map(), color_space="Raw")
    for prim, (name, inputs) in zip((floor, ball, glossy_ball, block), looks.items(), strict=True):
        material, shader = authoring.define_preview_material(stage, name, **inputs)
        if spec.normal_map and name != "Diffuse":
            authoring.connect_texture(
                material,
                shader,
                "normal",
                normal_file,
                source_color_space="raw",
                scale=(2, 2, 2, 1),
                bias=(-1, -1, -1, 0),
            )
        authoring.bind_material(prim.GetPrim(), material)
    camera = authoring.define_camera(
        stage,
        CAMERA,
        (0.3, 1.7, 3.9),
        (0.15, 0.45, -0.1),
        focal_length_mm=35.0,
        aperture_mm=(36.0, 27.0),
        clipping_range=(0.1, 1000.0),
    )
    authoring.define_render_settings(stage, camera, (spec.width, spec.height))
    _define_lights(stage, directory, spec.lighting)
    return authoring.save_stage(stage, directory / f"shot_{spec.lighting}.usda")


def _translation(x: float, y: float, z: float) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, 3] = (x, y, z)
    return matrix


def _define_lights(stage, directory: Path, lighting: str) -> None:
    if lighting == "sun":
        sun = UsdLux.DistantLight.Define(stage, "/World/Lights/Sun")
        authoring.set_light(sun.LightAPI(), intensity=DISTANT_RADIANCE)
        sun.CreateAngleAttr(0.53)
        authoring.place(sun, (0.0, 0.0, 0.0), rotate_xyz=(-50.0, 30.0, 0.0))
        return
    dome = UsdLux.DomeLight.Define(stage, DOME)
    if lighting == "constant":
        authoring.set_light(dome.LightAPI(), intensity=CONSTANT_RADIANCE)
        return
    if lighting == "latlong":
        write_rgb_exr(directory / "textures" / "sky.exr", sky_texture())
        authoring.set_light(dome.LightAPI(), intensity=1.0)
        dome.CreateTextureFileAttr("./textures/sky.exr")
    else:
        write_png(directory / "textures" / "sky.png", srgb_encode(sky_texture()), color_space="sRGB")
        authoring.set_light(dome.LightAPI(), intensity=CONSTANT_RADIANCE)
        dome.CreateTextureFileAttr("./textures/sky.png")
    dome.CreateTextureFormatAttr(UsdLux.Tokens.latlong)
    dome.AddRotateXYZOp().Set(Gf.Vec3f(*DOME_ROTATE_XYZ))
