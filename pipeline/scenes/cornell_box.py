"""The Cornell box, authored from its published measurements.

Source: Cornell University Program of Computer Graphics, "Cornell Box Data",
http://www.graphics.cornell.edu/online/box/data.html (last updated 2 February 2005; archived at
https://web.archive.org/web/2018/http://www.graphics.cornell.edu/online/box/data.html).

* Geometry: the measured vertices in millimetres, unchanged (the box is not quite rectangular:
  the floor is 552.8 wide at z = 0 and 549.6 at z = 559.2, the ceiling 556.0). The stage is in
  millimetres (metersPerUnit 0.001), +Y up. Each quad is wound so its front faces the inside of
  the box (walls) or away from its block (blocks), whatever order the page lists it in.
* Handedness: with the camera at (278, 273, -800) looking along +z with +y up, camera right is
  world -x in USD's right-handed frame, so the wall the data calls "left" (x ~ 552, red) is on the
  left of the image and the green wall (x = 0) on the right, as in the photographs.
  `tests/test_bundled_scenes.py` checks this by projecting the walls through the camera.
* Camera: focal length 35 mm, film 25 x 25 mm (USD: 350 and 250 tenths of a millimetre); square
  512 x 512 image by default.
* Materials: the measured paint reflectances (400-700 nm, 4 nm) converted to linear Rec.709 under
  D65 by `colorimetry.reflectance_to_linear_rec709` (perfect white -> (1, 1, 1)):
      white (floor, ceiling, back wall, blocks)  (0.7385, 0.7363, 0.7390)
      red   (left wall)                          (0.4932, 0.0489, 0.0512)
      green (right wall)                         (0.0686, 0.3986, 0.0865)
  "Surfaces are assumed to be Lambertian" (the data page). UsdPreviewSurface has no purely
  Lambertian setting; the closest is the specular workflow with specularColor 0 (F0 = 0) and
  roughness 1: normal-incidence specular is 0, but Storm's Schlick Fresnel still rises to 1 at
  grazing angles (F90 = 1), so a few per cent of grazing light is reflected broadly.
* Light: the measured opening, x 213..343, z 227..332 at y = 548.8 (130 x 105 mm = 0.01365 m^2),
  as a one-sided UsdLux RectLight emitting down (local -Z -> world -Y), 1 mm below the ceiling so
  the ceiling is kept whole as published. Its colour is the published emission spectrum
  (400: 0, 500: 8, 600: 15.6, 700: 18.4, relative) converted by
  `colorimetry.emission_to_linear_rec709` at unit luminance: (1.680, 0.876, 0.224), a tungsten
  lamp seen with a daylight (D65) white. The data's scale is arbitrary, so the intensity is ours:
  LIGHT_INTENSITY nits of luminance. Direct irradiance on the floor under the lamp is
  0.0448 x L (the 130 x 105 mm opening integrated at 547.8 mm), so the floor there reflects
  0.7385 / pi x 0.0448 x 1.680 x L = 0.0177 L in red directly: 0.44 with L = 25. Checked with a
  Mitsuba 3 path tracer on this layer (diffuse paints, 256 spp, 128 x 128): image median 0.18,
  99.9th percentile of the pixels below the lamp's rows 0.86, and 0.7 % of pixels above 1,
  nearly all of them the lamp itself.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Gf, UsdLux

from pipeline.scenes import authoring
from pipeline.scenes.bundled import BundledScene, LightEdit, LightOverride
from pipeline.scenes.colorimetry import emission_to_linear_rec709, reflectance_to_linear_rec709
from pipeline.scenes.meshes import orient_polygons, polygons

NAME = "cornell_box"
CAMERA = "/World/Camera"
LIGHT = "/World/Lights/CeilingLight"
RESOLUTION = (512, 512)
LIGHT_INTENSITY = 25.0
"""Luminance of the lamp in nits (its colour has unit luminance); see the module docstring."""
LIGHT_DROP_MM = 1.0
"""How far below the ceiling plane the lamp sits, so the two never coincide."""

REFLECTANCE_WAVELENGTHS_NM = np.arange(400.0, 701.0, 4.0)
REFLECTANCE = {
    "white": (
        0.343,
        0.445,
        0.551,
        0.624,
        0.665,
        0.687,
        0.708,
        0.723,
        0.715,
        0.710,
        0.745,
        0.758,
        0.739,
        0.767,
        0.777,
        0.765,
        0.751,
        0.745,
        0.748,
        0.729,
        0.745,
        0.757,
        0.753,
        0.750,
        0.746,
        0.747,
        0.735,
        0.732,
        0.739,
        0.734,
        0.725,
        0.721,
        0.733,
        0.725,
        0.732,
        0.743,
        0.744,
        0.748,
        0.728,
        0.716,
        0.733,
        0.726,
        0.713,
        0.740,
        0.754,
        0.764,
        0.752,
        0.736,
        0.734,
        0.741,
        0.740,
        0.732,
        0.745,
        0.755,
        0.751,
        0.744,
        0.731,
        0.733,
        0.744,
        0.731,
        0.712,
        0.708,
        0.729,
        0.730,
        0.727,
        0.707,
        0.703,
        0.729,
        0.750,
        0.760,
        0.751,
        0.739,
        0.724,
        0.730,
        0.740,
        0.737,
    ),
    "green": (
        0.092,
        0.096,
        0.098,
        0.097,
        0.098,
        0.095,
        0.095,
        0.097,
        0.095,
        0.094,
        0.097,
        0.098,
        0.096,
        0.101,
        0.103,
        0.104,
        0.107,
        0.109,
        0.112,
        0.115,
        0.125,
        0.140,
        0.160,
        0.187,
        0.229,
        0.285,
        0.343,
        0.390,
        0.435,
        0.464,
        0.472,
        0.476,
        0.481,
        0.462,
        0.447,
        0.441,
        0.426,
        0.406,
        0.373,
        0.347,
        0.337,
        0.314,
        0.285,
        0.277,
        0.266,
        0.250,
        0.230,
        0.207,
        0.186,
        0.171,
        0.160,
        0.148,
        0.141,
        0.136,
        0.130,
        0.126,
        0.123,
        0.121,
        0.122,
        0.119,
        0.114,
        0.115,
        0.117,
        0.117,
        0.118,
        0.120,
        0.122,
        0.128,
        0.132,
        0.139,
        0.144,
        0.146,
        0.150,
        0.152,
        0.157,
        0.159,
    ),
    "red": (
        0.040,
        0.046,
        0.048,
        0.053,
        0.049,
        0.050,
        0.053,
        0.055,
        0.057,
        0.056,
        0.059,
        0.057,
        0.061,
        0.061,
        0.060,
        0.062,
        0.062,
        0.062,
        0.061,
        0.062,
        0.060,
        0.059,
        0.057,
        0.058,
        0.058,
        0.058,
        0.056,
        0.055,
        0.056,
        0.059,
        0.057,
        0.055,
        0.059,
        0.059,
        0.058,
        0.059,
        0.061,
        0.061,
        0.063,
        0.063,
        0.067,
        0.068,
        0.072,
        0.080,
        0.090,
        0.099,
        0.124,
        0.154,
        0.192,
        0.255,
        0.287,
        0.349,
        0.402,
        0.443,
        0.487,
        0.513,
        0.558,
        0.584,
        0.620,
        0.606,
        0.609,
        0.651,
        0.612,
        0.610,
        0.650,
        0.638,
        0.627,
        0.620,
        0.630,
        0.628,
        0.642,
        0.639,
        0.657,
        0.639,
        0.635,
        0.642,
    ),
}
"""Measured spectral reflectance of the paints at REFLECTANCE_WAVELENGTHS_NM (76 samples)."""

EMISSION_WAVELENGTHS_NM = np.array([400.0, 500.0, 600.0, 700.0])
EMISSION = np.array([0.0, 8.0, 15.6, 18.4])
"""Relative spectral emission of the lamp (the page: 'relative only; their scales are arbitrary')."""

CAMERA_POSITION = (278.0, 273.0, -800.0)
LIGHT_X = (213.0, 343.0)
LIGHT_Z = (227.0, 332.0)
CEILING_Y = 548.8

# (name, paint, quads as listed on the data page). Walls face the box's interior, blocks outwards.
_WALLS = (
    ("Floor", "white", ((552.8, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 559.2), (549.6, 0.0, 559.2))),
    ("Ceiling", "white", ((556.0, 548.8, 0.0), (556.0, 548.8, 559.2), (0.0, 548.8, 559.2), (0.0, 548.8, 0.0))),
    ("BackWall", "white", ((549.6, 0.0, 559.2), (0.0, 0.0, 559.2), (0.0, 548.8, 559.2), (556.0, 548.8, 559.2))),
    ("RightWall", "green", ((0.0, 0.0, 559.2), (0.0, 0.0, 0.0), (0.0, 548.8, 0.0), (0.0, 548.8, 559.2))),
    ("LeftWall", "red", ((552.8, 0.0, 0.0), (549.6, 0.0, 559.2), (556.0, 548.8, 559.2), (556.0, 548.8, 0.0))),
)
_BLOCKS = (
    (
        "ShortBlock",
        (
            ((130.0, 165.0, 65.0), (82.0, 165.0, 225.0), (240.0, 165.0, 272.0), (290.0, 165.0, 114.0)),
            ((290.0, 0.0, 114.0), (290.0, 165.0, 114.0), (240.0, 165.0, 272.0), (240.0, 0.0, 272.0)),
            ((130.0, 0.0, 65.0), (130.0, 165.0, 65.0), (290.0, 165.0, 114.0), (290.0, 0.0, 114.0)),
            ((82.0, 0.0, 225.0), (82.0, 165.0, 225.0), (130.0, 165.0, 65.0), (130.0, 0.0, 65.0)),
            ((240.0, 0.0, 272.0), (240.0, 165.0, 272.0), (82.0, 165.0, 225.0), (82.0, 0.0, 225.0)),
        ),
    ),
    (
        "TallBlock",
        (
            ((423.0, 330.0, 247.0), (265.0, 330.0, 296.0), (314.0, 330.0, 456.0), (472.0, 330.0, 406.0)),
            ((423.0, 0.0, 247.0), (423.0, 330.0, 247.0), (472.0, 330.0, 406.0), (472.0, 0.0, 406.0)),
            ((472.0, 0.0, 406.0), (472.0, 330.0, 406.0), (314.0, 330.0, 456.0), (314.0, 0.0, 456.0)),
            ((314.0, 0.0, 456.0), (314.0, 330.0, 456.0), (265.0, 330.0, 296.0), (265.0, 0.0, 296.0)),
            ((265.0, 0.0, 296.0), (265.0, 330.0, 296.0), (423.0, 330.0, 247.0), (423.0, 0.0, 247.0)),
        ),
    ),
)


def paint_rgb(paint: str) -> np.ndarray:
    """(3,) linear Rec.709 albedo of a measured paint ('white', 'red', 'green') under D65."""
    return reflectance_to_linear_rec709(REFLECTANCE_WAVELENGTHS_NM, np.asarray(REFLECTANCE[paint]))


def light_color() -> np.ndarray:
    """(3,) linear Rec.709 colour of the lamp at unit luminance."""
    return emission_to_linear_rec709(EMISSION_WAVELENGTHS_NM, EMISSION)


def box_center() -> np.ndarray:
    """(3,) the centre of the box's bounding volume, used to orient the walls."""
    corners = np.array([quad for _, _, quad in _WALLS]).reshape(-1, 3)
    return 0.5 * (corners.min(axis=0) + corners.max(axis=0))


def write(directory: Path) -> Path:
    """Write DIR/cornell_box.usda and return its path."""
    stage = authoring.create_stage(
        0.001, "Cornell box from the published Cornell Program of Computer Graphics data (millimetres)."
    )
    materials = {}
    for paint in REFLECTANCE:
        materials[paint], _ = authoring.define_preview_material(
            stage,
            paint.capitalize(),
            diffuseColor=paint_rgb(paint),
            useSpecularWorkflow=1,
            specularColor=(0.0, 0.0, 0.0),
            roughness=1.0,
        )

    center = box_center()
    for name, paint, quad in _WALLS:
        corners = np.array([quad])
        corners = orient_polygons(corners, center - corners.mean(axis=1))
        mesh = authoring.define_mesh(stage, f"/World/Geometry/{name}", polygons(corners))
        authoring.bind_material(mesh.GetPrim(), materials[paint])
    for name, quads in _BLOCKS:
        corners = np.array(quads)
        corners = orient_polygons(corners, corners.mean(axis=1) - corners.reshape(-1, 3).mean(axis=0))
        mesh = authoring.define_mesh(stage, f"/World/Geometry/{name}", polygons(corners))
        authoring.bind_material(mesh.GetPrim(), materials["white"])

    light = UsdLux.RectLight.Define(stage, LIGHT)
    light.CreateWidthAttr(LIGHT_X[1] - LIGHT_X[0])
    light.CreateHeightAttr(LIGHT_Z[1] - LIGHT_Z[0])
    authoring.set_light(light.LightAPI(), intensity=LIGHT_INTENSITY, color=light_color())
    authoring.place_aimed(
        light,
        (np.mean(LIGHT_X), CEILING_Y - LIGHT_DROP_MM, np.mean(LIGHT_Z)),
        (np.mean(LIGHT_X), 0.0, np.mean(LIGHT_Z)),
    )

    camera = authoring.define_camera(
        stage,
        CAMERA,
        CAMERA_POSITION,
        np.add(CAMERA_POSITION, (0.0, 0.0, 1.0)),
        focal_length_mm=35.0,
        aperture_mm=(25.0, 25.0),
        clipping_range=(10.0, 1.0e5),
    )
    authoring.define_render_settings(stage, camera, RESOLUTION)
    return authoring.save_stage(stage, Path(directory) / f"{NAME}.usda")


LIGHT_EDITS = (
    LightEdit(
        "move",
        "slide the lamp 100 mm towards the red wall and 80 mm towards the back",
        (
            LightOverride(
                LIGHT,
                {
                    "xformOp:translate": (
                        "double3",
                        Gf.Vec3d(
                            float(np.mean(LIGHT_X)) + 100.0, CEILING_Y - LIGHT_DROP_MM, float(np.mean(LIGHT_Z)) + 80.0
                        ),
                    )
                },
            ),
        ),
    ),
    LightEdit(
        "white_light",
        "the same luminance with a white (D65) lamp",
        (LightOverride(LIGHT, {"inputs:color": ("color3f", Gf.Vec3f(1.0, 1.0, 1.0))}),),
    ),
    LightEdit(
        "focus",
        "focus the lamp downwards (ShapingAPI focus 4) and double its intensity",
        (
            LightOverride(
                LIGHT,
                {"inputs:shaping:focus": ("float", 4.0), "inputs:intensity": ("float", 2.0 * LIGHT_INTENSITY)},
                api_schemas=("ShapingAPI",),
            ),
        ),
    ),
)

SCENE = BundledScene(
    name=NAME,
    camera=CAMERA,
    description="Cornell box from the published measurements (mm, spectral paints -> Rec.709, rect light)",
    write=write,
    light_edits=LIGHT_EDITS,
)
