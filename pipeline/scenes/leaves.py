"""Cut-out leaves and a lattice fence casting shadows on a floor: the opacity test scene.

Stage in centimetres (metersPerUnit 0.01), +Y up, 640 x 480.

Objects:
    Floor       300 x 300 cm quad, light grey diffuse (0.6), roughness 0.9
    Leaf0..5    40 x 40 cm quads (doubleSided), tilted 15-35 degrees, at heights 35-95 cm
                above the floor; a generated RGBA leaf texture (sRGB colour, binary alpha) feeds
                diffuseColor ('rgb') and opacity ('a'), opacityThreshold 0.5: the quad outside the
                leaf's outline and the holes along its midrib are cut out
    Fence       a vertical 160 x 80 cm quad at the back, a generated lattice (bars 1/3 of the
                period) in its alpha, opacityThreshold 0.5
Textures are written beside the layer under textures/ (8-bit PNG, alpha exactly 0 or 1).

Lights (radiance L = intensity, normalize off):
    Key     SphereLight r = 8 cm at (-120, 220, 120), intensity 250: at the floor centre
            (d ~ 280 cm) E = pi L (r / d)^2 ~ 0.64, so the floor (albedo 0.6) reflects ~0.12; placed so
            that the sun does not cast its sphere's shadow on the floor (Mitsuba's emitter shapes
            occlude, ours do not)
    Sun     DistantLight, angle 1 degree, travelling along (-0.35, -0.9, -0.25): crisp leaf
            shadows; intensity SUN_IRRADIANCE / (pi sin^2(0.5 deg)) gives E = 2.2 cos ~ 2.0 on the
            floor, which reflects 0.6 E / pi ~ 0.38
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Gf, UsdLux

from pipeline.scenes import authoring
from pipeline.scenes.bundled import BundledScene, LightEdit, LightOverride
from pipeline.scenes.meshes import plane
from pipeline.scenes.textures import srgb_encode, write_png

NAME = "leaves"
CAMERA = "/World/Camera"
KEY = "/World/Lights/Key"
SUN = "/World/Lights/Sun"
RESOLUTION = (640, 480)
TEXTURE_DIR = "textures"
TEXTURE_SIZE = 256
THRESHOLD = 0.5

# (centre (x, y, z) cm, rotation XYZ degrees) of each leaf quad.
LEAVES = (
    ((-55.0, 60.0, 20.0), (-25.0, 20.0, 10.0)),
    ((5.0, 80.0, -25.0), (20.0, -35.0, 15.0)),
    ((55.0, 45.0, 35.0), (-15.0, 60.0, -20.0)),
    ((-10.0, 95.0, 55.0), (30.0, 100.0, 0.0)),
    ((45.0, 35.0, -55.0), (-35.0, -120.0, 10.0)),
    ((-60.0, 40.0, -45.0), (15.0, 150.0, -30.0)),
)
LEAF_SIZE = 40.0
KEY_POSITION = (-120.0, 220.0, 120.0)
SUN_IRRADIANCE = 2.2
"""Irradiance of the sun on a surface facing it."""


def leaf_texture(size: int = TEXTURE_SIZE) -> np.ndarray:
    """(size, size, 4) linear RGBA of a leaf: green blade with darker veins, alpha 1 inside its
    outline (a lens between two circular arcs, pointed at both ends), 0 outside and in small
    holes along the midrib."""
    centres = (np.arange(size) + 0.5) / size
    s, t = np.meshgrid(centres, 1.0 - centres)  # row 0 is the top: t = 1
    x, y = 2.0 * s - 1.0, 2.0 * t - 1.0  # the midrib runs along y
    # Lens: inside both circles of radius R centred at (+-c, 0) through the tips (0, +-0.95).
    half_width, tip = 0.45, 0.95
    centre = (tip**2 - half_width**2) / (2.0 * half_width)
    radius = centre + half_width
    inside = ((x - centre) ** 2 + y**2 <= radius**2) & ((x + centre) ** 2 + y**2 <= radius**2)
    holes = np.zeros_like(inside)
    for hole_y in (-0.45, 0.0, 0.45):
        holes |= (x - 0.15) ** 2 + (y - hole_y) ** 2 < 0.06**2
    alpha = (inside & ~holes).astype(np.float64)
    veins = (np.abs(x) < 0.02) | (np.abs(np.mod(y - 0.8 * np.abs(x), 0.25) - 0.125) < 0.012)
    colour = np.where(veins[..., None], (0.10, 0.22, 0.05), (0.18, 0.45, 0.08))
    return np.concatenate([colour, alpha[..., None]], axis=-1)


def lattice_texture(size: int = TEXTURE_SIZE, periods: int = 6) -> np.ndarray:
    """(size, size, 4) linear RGBA of a wooden lattice: diagonal bars (a third of each period)
    in both directions, alpha 1 on the bars and 0 between them."""
    centres = (np.arange(size) + 0.5) / size
    s, t = np.meshgrid(centres, centres)
    bar = lambda u: np.mod(u * periods, 1.0) < 1.0 / 3.0  # noqa: E731
    alpha = (bar(s + t) | bar(s - t + 1.0)).astype(np.float64)
    colour = np.broadcast_to(np.array([0.45, 0.30, 0.18]), alpha.shape + (3,))
    return np.concatenate([colour, alpha[..., None]], axis=-1)


def _write_texture(path: Path, rgba: np.ndarray) -> Path:
    """An 8-bit sRGB PNG of linear RGBA (alpha stored as is)."""
    encoded = np.concatenate([srgb_encode(rgba[..., :3]), rgba[..., 3:]], axis=-1)
    return write_png(path, np.ascontiguousarray(encoded), color_space="sRGB")


def _cutout_material(stage, name: str, file: str):
    material, shader = authoring.define_preview_material(
        stage, name, roughness=0.7, metallic=0.0, opacityThreshold=THRESHOLD
    )
    authoring.connect_texture(material, shader, "diffuseColor", file, source_color_space="sRGB")
    authoring.connect_texture(material, shader, "opacity", file, source_color_space="sRGB", output="a")
    return material


def write(directory: Path) -> Path:
    """Write DIR/leaves.usda and its textures under DIR/textures/; return the layer's path."""
    directory = Path(directory)
    leaf = _write_texture(directory / TEXTURE_DIR / f"{NAME}_leaf.png", leaf_texture())
    lattice = _write_texture(directory / TEXTURE_DIR / f"{NAME}_lattice.png", lattice_texture())
    stage = authoring.create_stage(0.01, "Opacity test scene: cut-out leaves and a lattice over a floor (centimetres).")
    floor_material, _ = authoring.define_preview_material(
        stage, "Floor", diffuseColor=(0.6, 0.6, 0.6), roughness=0.9, metallic=0.0
    )
    leaf_material = _cutout_material(stage, "Leaf", f"./{TEXTURE_DIR}/{leaf.name}")
    lattice_material = _cutout_material(stage, "Lattice", f"./{TEXTURE_DIR}/{lattice.name}")
    geometry = authoring.GEOMETRY
    floor = authoring.define_mesh(stage, f"{geometry}/Floor", plane(300.0, 300.0))
    authoring.bind_material(floor.GetPrim(), floor_material)
    for index, (centre, rotation) in enumerate(LEAVES):
        quad = authoring.define_mesh(stage, f"{geometry}/Leaf{index}", plane(LEAF_SIZE, LEAF_SIZE))
        quad.CreateDoubleSidedAttr(True)
        authoring.place(quad, centre, rotate_xyz=rotation)
        authoring.bind_material(quad.GetPrim(), leaf_material)
    fence = authoring.define_mesh(stage, f"{geometry}/Fence", plane(160.0, 80.0, st_repeat=1.0))
    fence.CreateDoubleSidedAttr(True)
    authoring.place(fence, (0.0, 40.0, -100.0), rotate_xyz=(90.0, 0.0, 0.0))
    authoring.bind_material(fence.GetPrim(), lattice_material)

    key = UsdLux.SphereLight.Define(stage, KEY)
    key.CreateRadiusAttr(8.0)
    authoring.set_light(key.LightAPI(), intensity=250.0, color=(1.0, 0.95, 0.85))
    authoring.place(key, KEY_POSITION)
    sun = UsdLux.DistantLight.Define(stage, SUN)
    sun.CreateAngleAttr(1.0)
    authoring.set_light(
        sun.LightAPI(), intensity=SUN_IRRADIANCE / (np.pi * np.sin(np.radians(0.5)) ** 2), color=(1.0, 0.98, 0.95)
    )
    authoring.place(sun, (0.0, 0.0, 0.0), rotate_xyz=authoring.aim_rotation_xyz(np.array([-0.35, -0.9, -0.25])))
    camera = authoring.define_camera(
        stage,
        CAMERA,
        (0.0, 190.0, 230.0),
        (0.0, 20.0, -10.0),
        focal_length_mm=35.0,
        aperture_mm=(36.0, 27.0),
        clipping_range=(1.0, 1.0e4),
    )
    authoring.define_render_settings(stage, camera, RESOLUTION)
    return authoring.save_stage(stage, directory / f"{NAME}.usda")


LIGHT_EDITS = (
    LightEdit(
        "move",
        "move the key light low to the right, lengthening the leaves' shadows",
        (LightOverride(KEY, {"xformOp:translate": ("double3", Gf.Vec3d(180.0, 120.0, 60.0))}),),
    ),
    LightEdit(
        "turn_sun",
        "turn the sun to come from the front right",
        (
            LightOverride(
                SUN, {"xformOp:rotateXYZ": ("float3", authoring.aim_rotation_xyz(np.array([0.4, -0.8, -0.45])))}
            ),
        ),
    ),
    LightEdit(
        "warm_key",
        "warm the key light and double it",
        (
            LightOverride(
                KEY, {"inputs:color": ("color3f", Gf.Vec3f(1.0, 0.7, 0.45)), "inputs:intensity": ("float", 500.0)}
            ),
        ),
    ),
)

SCENE = BundledScene(
    name=NAME,
    camera=CAMERA,
    description="alpha-textured cut-out leaves and a lattice fence over a floor (opacity + opacityThreshold); "
    "sphere light + sun",
    write=write,
    light_edits=LIGHT_EDITS,
)
