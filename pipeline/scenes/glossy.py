"""A glossy-materials scene: metals and plastics on a brick floor under a sphere light and a spot.

Stage in centimetres (metersPerUnit 0.01), +Y up, 640 x 480.

Objects (on an 800 x 800 cm brick floor, in front of a 300 cm high grey backdrop):
    GoldSphere          UsdGeom.Sphere (implicit), metallic 1, roughness 0.2
    CopperSphere        mesh uv sphere with normals + st, metallic 1, roughness 0.4
    AluminiumTorus      mesh torus with normals + st, metallic 1, roughness 0.7
    RedPlasticCylinder  UsdGeom.Cylinder (implicit), metallic 0, roughness 0.3
    BluePlasticCube     UsdGeom.Cube (implicit), specular workflow (specularColor 0.04), roughness 0.15
    Floor               mesh with st, brick albedo (sRGB PNG) + tangent-space normal map (raw PNG,
                        scale (2, 2, 2, 1), bias (-1, -1, -1, 0)), roughness 0.8, written beside the
                        layer under textures/
Metal colours are linear F0 reflectances (N. Hoffman, "Physics and Math of Shading", SIGGRAPH 2015
course): gold (1.00, 0.71, 0.29), copper (0.95, 0.64, 0.54), aluminium (0.91, 0.92, 0.92).

Lights and exposure (radiance L = intensity, normalize off; E = pi L (r / d)^2 for a sphere light):
    Key   SphereLight r = 15 cm at (150, 220, 180), intensity 600: at the floor centre (d = 321 cm,
          cos 0.69) E = 2.8, so the bricks (mean albedo ~0.33) reflect ~0.3.
    Spot  SphereLight r = 4 cm at (-170, 170, 120) aimed at the gold sphere, ShapingAPI cone 22 deg,
          softness 0.3, focus 1, intensity 4000: on the floor under the sphere (d ~ 210 cm) E ~ 4.6,
          reflected ~0.5.
Checked with a Mitsuba 3 path tracer on this layer (metals as rough conductors, plastics as rough
plastics, 64 spp): median pixel 0.16, 99th percentile 0.94, 0.9 % of pixels above 1 (the metals'
mirror-like highlights of the small lights, which should exceed 1).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Gf, UsdGeom, UsdLux

from pipeline.scenes import authoring
from pipeline.scenes.bundled import BundledScene, LightEdit, LightOverride
from pipeline.scenes.meshes import box, plane, torus, uv_sphere
from pipeline.scenes.textures import write_brick_textures

NAME = "glossy"
CAMERA = "/World/Camera"
KEY = "/World/Lights/Key"
SPOT = "/World/Lights/Spot"
RESOLUTION = (640, 480)
TEXTURE_DIR = "textures"

GOLD_POSITION = (-90.0, 30.0, 0.0)
KEY_POSITION = (150.0, 220.0, 180.0)
SPOT_POSITION = (-170.0, 170.0, 120.0)
KEY_INTENSITY = 600.0
SPOT_INTENSITY = 4000.0

METALS = {
    "Gold": ((1.00, 0.71, 0.29), 0.2),
    "Copper": ((0.95, 0.64, 0.54), 0.4),
    "Aluminium": ((0.91, 0.92, 0.92), 0.7),
}
"""name -> (linear F0 colour, roughness)."""


def _define_materials(stage, albedo_file: str, normal_file: str) -> dict:
    materials = {}
    for name, (color, roughness) in METALS.items():
        materials[name], _ = authoring.define_preview_material(
            stage, name, diffuseColor=color, metallic=1.0, roughness=roughness
        )
    materials["RedPlastic"], _ = authoring.define_preview_material(
        stage, "RedPlastic", diffuseColor=(0.60, 0.05, 0.04), metallic=0.0, roughness=0.3
    )
    materials["BluePlastic"], _ = authoring.define_preview_material(
        stage,
        "BluePlastic",
        diffuseColor=(0.05, 0.15, 0.50),
        useSpecularWorkflow=1,
        specularColor=(0.04, 0.04, 0.04),
        roughness=0.15,
    )
    materials["Backdrop"], _ = authoring.define_preview_material(
        stage, "Backdrop", diffuseColor=(0.35, 0.35, 0.35), metallic=0.0, roughness=0.9
    )
    bricks, shader = authoring.define_preview_material(stage, "Bricks", metallic=0.0, roughness=0.8)
    authoring.connect_texture(bricks, shader, "diffuseColor", albedo_file, source_color_space="sRGB")
    authoring.connect_texture(
        bricks,
        shader,
        "normal",
        normal_file,
        source_color_space="raw",
        scale=(2.0, 2.0, 2.0, 1.0),
        bias=(-1.0, -1.0, -1.0, 0.0),
    )
    materials["Bricks"] = bricks
    return materials


def _define_geometry(stage, materials: dict) -> None:
    geometry = authoring.GEOMETRY

    floor = authoring.define_mesh(stage, f"{geometry}/Floor", plane(800.0, 800.0, st_repeat=8.0))
    backdrop = authoring.define_mesh(stage, f"{geometry}/Backdrop", box((800.0, 300.0, 20.0), (0.0, 150.0, -260.0)))

    gold = UsdGeom.Sphere.Define(stage, f"{geometry}/GoldSphere")
    gold.CreateRadiusAttr(30.0)
    gold.CreateExtentAttr([(-30.0, -30.0, -30.0), (30.0, 30.0, 30.0)])
    authoring.place(gold, GOLD_POSITION)

    copper = authoring.define_mesh(stage, f"{geometry}/CopperSphere", uv_sphere(30.0, 64, 32))
    authoring.place(copper, (0.0, 30.0, -70.0))

    aluminium = authoring.define_mesh(stage, f"{geometry}/AluminiumTorus", torus(25.0, 10.0, 64, 24))
    authoring.place(aluminium, (95.0, 10.0, 10.0))

    cylinder = UsdGeom.Cylinder.Define(stage, f"{geometry}/RedPlasticCylinder")
    cylinder.CreateRadiusAttr(15.0)
    cylinder.CreateHeightAttr(50.0)
    cylinder.CreateAxisAttr(UsdGeom.Tokens.y)
    cylinder.CreateExtentAttr([(-15.0, -25.0, -15.0), (15.0, 25.0, 15.0)])
    authoring.place(cylinder, (-35.0, 25.0, 80.0))

    cube = UsdGeom.Cube.Define(stage, f"{geometry}/BluePlasticCube")
    cube.CreateSizeAttr(35.0)
    cube.CreateExtentAttr([(-17.5, -17.5, -17.5), (17.5, 17.5, 17.5)])
    authoring.place(cube, (45.0, 17.5, 85.0), rotate_xyz=(0.0, 30.0, 0.0))

    for prim, material in (
        (floor, "Bricks"),
        (backdrop, "Backdrop"),
        (gold, "Gold"),
        (copper, "Copper"),
        (aluminium, "Aluminium"),
        (cylinder, "RedPlastic"),
        (cube, "BluePlastic"),
    ):
        authoring.bind_material(prim.GetPrim(), materials[material])


def _define_lights(stage) -> None:
    key = UsdLux.SphereLight.Define(stage, KEY)
    key.CreateRadiusAttr(15.0)
    authoring.set_light(key.LightAPI(), intensity=KEY_INTENSITY, color=(1.0, 0.96, 0.9))
    authoring.place(key, KEY_POSITION)

    spot = UsdLux.SphereLight.Define(stage, SPOT)
    spot.CreateRadiusAttr(4.0)
    authoring.set_light(spot.LightAPI(), intensity=SPOT_INTENSITY, color=(0.9, 0.95, 1.0))
    authoring.shape_spot(spot.GetPrim(), cone_angle=22.0, softness=0.3, focus=1.0)
    authoring.place_aimed(spot, SPOT_POSITION, GOLD_POSITION)


def write(directory: Path) -> Path:
    """Write DIR/glossy.usda and its textures under DIR/textures/; return the layer's path."""
    directory = Path(directory)
    albedo, normal = write_brick_textures(directory / TEXTURE_DIR, NAME)
    stage = authoring.create_stage(0.01, "Glossy test scene: metals, plastics, a textured floor (centimetres).")
    materials = _define_materials(stage, f"./{TEXTURE_DIR}/{albedo.name}", f"./{TEXTURE_DIR}/{normal.name}")
    _define_geometry(stage, materials)
    _define_lights(stage)
    camera = authoring.define_camera(
        stage,
        CAMERA,
        (0.0, 110.0, 380.0),
        (0.0, 25.0, 0.0),
        focal_length_mm=35.0,
        aperture_mm=(36.0, 27.0),
        clipping_range=(1.0, 1.0e4),
    )
    authoring.define_render_settings(stage, camera, RESOLUTION)
    return authoring.save_stage(stage, directory / f"{NAME}.usda")


LIGHT_EDITS = (
    LightEdit(
        "move",
        "move the key light to the camera's left and lower it",
        (LightOverride(KEY, {"xformOp:translate": ("double3", Gf.Vec3d(-180.0, 140.0, 150.0))}),),
    ),
    LightEdit(
        "reaim_spot",
        "re-aim the spot from the gold sphere to the aluminium torus",
        (
            LightOverride(
                SPOT,
                {
                    "xformOp:rotateXYZ": (
                        "float3",
                        authoring.aim_rotation_xyz(np.subtract((95.0, 10.0, 10.0), SPOT_POSITION)),
                    )
                },
            ),
        ),
    ),
    LightEdit(
        "colour_shaping",
        "warm the spot and widen its cone with a softer edge",
        (
            LightOverride(
                SPOT,
                {
                    "inputs:color": ("color3f", Gf.Vec3f(1.0, 0.6, 0.3)),
                    "inputs:shaping:cone:angle": ("float", 35.0),
                    "inputs:shaping:cone:softness": ("float", 0.8),
                },
            ),
        ),
    ),
)

SCENE = BundledScene(
    name=NAME,
    camera=CAMERA,
    description="metals (gold/copper/aluminium) and plastics on a brick-textured, normal-mapped floor; "
    "sphere light + spot",
    write=write,
    light_edits=LIGHT_EDITS,
)
