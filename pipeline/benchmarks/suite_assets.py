"""The real-asset suite: public USD assets of tests/data/scene framed into shots.

Each `SuiteAsset` writes its shot into a work folder and names the camera to bake: the Utah
teapot shot (usd-wg/assets, CC0) as committed; OpenUSD's UsdPreviewSurface test scenes, which
have no camera or lights, framed by `frame_asset` (a camera on a diagonal towards the stage's
bounds, a distant light and a sphere light, the asset as a sublayer); and `write_exterior_shot`,
an exterior with open sky of instanced and point-instanced Utah teapots (`python -m
tests.sky_support DIR --teapots N` writes it for measurements). Provenance and licences:
tests/data/scene/PROVENANCE.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pxr import Usd, UsdGeom

from pipeline.errors import RelightError

SCENE_DATA = Path(__file__).resolve().parents[2] / "tests" / "data" / "scene"
"""The committed assets (a source checkout's tests/data/scene)."""


TEAPOT = SCENE_DATA / "usdwg_teapot" / "Teapot.usd"

# Camera prim -> (position, look-at point); the stage is Y-up, metres.
CAMERAS = {
    "Horizon": ((0.0, 0.25, 2.5), (0.0, 0.25, 0.0)),  # level: sky above the horizon, floor below
    "Sky": ((0.0, 0.5, 0.0), (0.0, 10.0, 0.01)),  # straight up: nothing but sky
    "Close": ((0.35, 0.3, 0.45), (0.0, 0.1, 0.0)),  # one teapot filling the frame
    "Inside": ((3.0, 0.5, 3.0), (3.0, 0.5, 0.0)),  # inside the closed /Shot/Box
}


def _look_at(
    eye: tuple[float, float, float],
    target: tuple[float, float, float],
    up: tuple[float, float, float] = (0.0, 1.0, 0.0),
) -> list[list[float]]:
    """USD row-vector world-from-camera matrix of a camera at `eye` looking at `target` (`up` up)."""
    forward = [t - e for t, e in zip(target, eye, strict=True)]
    norm = math.sqrt(sum(f * f for f in forward))
    back = [-f / norm for f in forward]
    if abs(sum(b * u for b, u in zip(back, up, strict=True))) >= 0.99:  # looking along the up axis
        up = (0.0, 0.0, -1.0) if up[1] else (0.0, 1.0, 0.0)
    right = [up[1] * back[2] - up[2] * back[1], up[2] * back[0] - up[0] * back[2], up[0] * back[1] - up[1] * back[0]]
    norm = math.sqrt(sum(r * r for r in right))
    right = [r / norm for r in right]
    true_up = [
        back[1] * right[2] - back[2] * right[1],
        back[2] * right[0] - back[0] * right[2],
        back[0] * right[1] - back[1] * right[0],
    ]
    return [right + [0.0], true_up + [0.0], back + [0.0], list(eye) + [1.0]]


def _matrix(rows: list[list[float]]) -> str:
    return "(" + ", ".join("(" + ", ".join(f"{v:.9g}" for v in row) + ")" for row in rows) + ")"


def write_exterior_shot(
    directory: Path, teapots: int = 8, sphere_lights: int = 4, width: int = 32, height: int = 24
) -> Path:
    """Write `directory`/exterior.usda and return its path.

    Args:
        teapots: teapots in all, half as instanceable references on a row, half as one
            PointInstancer's instances on a grid behind them (2,472 triangles each).
        sphere_lights: coloured sphere lights in a ring above the teapots (plus a distant sun of 2 lux).
        width, height: the RenderSettings resolution.
    """
    directory.mkdir(parents=True, exist_ok=True)
    teapot = TEAPOT.resolve().as_posix()
    referenced = teapots // 2
    instanced = teapots - referenced
    side = max(1, math.ceil(math.sqrt(instanced)))
    lines = [
        "#usda 1.0",
        "(",
        '    defaultPrim = "Shot"',
        "    metersPerUnit = 1",
        '    upAxis = "Y"',
        ")",
        "",
        'def Xform "Shot"',
        "{",
    ]
    lines += [
        '    def Scope "Render"',
        "    {",
        '        def RenderSettings "Settings"',
        "        {",
        f"            uniform int2 resolution = ({width}, {height})",
        "        }",
        "    }",
    ]
    lines += ['    def Xform "Cams"', "    {"]
    for name, (eye, target) in CAMERAS.items():
        lines += [
            f'        def Camera "{name}"',
            "        {",
            "            float2 clippingRange = (0.01, 1000)",
            "            float focalLength = 24",
            "            float horizontalAperture = 36",
            "            float verticalAperture = 27",
            f"            matrix4d xformOp:transform = {_matrix(_look_at(eye, target))}",
            '            uniform token[] xformOpOrder = ["xformOp:transform"]',
            "        }",
        ]
    lines += ["    }"]
    # Referenced teapots on a row along x (instanceable: one prototype).
    lines += ['    def Xform "Row"', "    {"]
    for i in range(referenced):
        x = 0.6 * (i - (referenced - 1) / 2)
        lines += [
            f'        def "Teapot{i}" (',
            f"            prepend references = @{teapot}@",
            "            instanceable = true",
            "        )",
            "        {",
            f"            double3 xformOp:translate = ({x:.6g}, 0, 0)",
            '            uniform token[] xformOpOrder = ["xformOp:translate"]',
            "        }",
        ]
    lines += ["    }"]
    if instanced:
        positions = [(0.6 * (k % side - (side - 1) / 2), 0.0, -1.0 - 0.6 * (k // side)) for k in range(instanced)]
        lines += [
            '    def PointInstancer "Grid"',
            "    {",
            "        int[] protoIndices = [" + ", ".join("0" for _ in positions) + "]",
            "        point3f[] positions = ["
            + ", ".join(f"({x:.6g}, {y:.6g}, {z:.6g})" for x, y, z in positions)
            + "]",
            "        rel prototypes = </Shot/Grid/Prototypes/Teapot>",
            '        def Scope "Prototypes"',
            "        {",
            '            def "Teapot" (',
            f"                prepend references = @{teapot}@",
            "            )",
            "            {",
            "            }",
            "        }",
            "    }",
        ]
    # A floor far wider than the view, so the horizon sits near the middle of the level camera.
    lines += [
        '    def Mesh "Floor" (',
        '        prepend apiSchemas = ["MaterialBindingAPI"]',
        "    )",
        "    {",
        "        int[] faceVertexCounts = [4]",
        "        int[] faceVertexIndices = [0, 3, 2, 1]",
        "        rel material:binding = </Shot/Looks/Floor>",
        "        point3f[] points = [(-200, 0, -200), (200, 0, -200), (200, 0, 200), (-200, 0, 200)]",
        '        uniform token subdivisionScheme = "none"',
        "    }",
    ]
    # A closed box away from the teapots, for a camera inside geometry.
    lines += [
        '    def Cube "Box" (',
        '        prepend apiSchemas = ["MaterialBindingAPI"]',
        "    )",
        "    {",
        "        double size = 1",
        "        rel material:binding = </Shot/Looks/Floor>",
        "        double3 xformOp:translate = (3, 0.5, 3)",
        '        uniform token[] xformOpOrder = ["xformOp:translate"]',
        "    }",
    ]
    lines += [
        '    def Scope "Looks"',
        "    {",
        '        def Material "Floor"',
        "        {",
        "            token outputs:surface.connect = </Shot/Looks/Floor/Surface.outputs:surface>",
        '            def Shader "Surface"',
        "            {",
        '                uniform token info:id = "UsdPreviewSurface"',
        "                color3f inputs:diffuseColor = (0.45, 0.42, 0.38)",
        "                float inputs:roughness = 0.8",
        "                token outputs:surface",
        "            }",
        "        }",
        "    }",
    ]
    lines += [
        '    def Scope "Lights"',
        "    {",
        '        def DistantLight "Sun"',
        "        {",
        "            float inputs:angle = 1",
        "            float inputs:intensity = 2",
        "            bool inputs:normalize = 1",  # 2 lux: without it a 1-degree sun gives 5e-4
        "            color3f inputs:color = (1, 0.95, 0.85)",
        "            float3 xformOp:rotateXYZ = (-50, 30, 0)",
        '            uniform token[] xformOpOrder = ["xformOp:rotateXYZ"]',
        "        }",
    ]
    for k in range(sphere_lights):
        angle = 2 * math.pi * k / max(sphere_lights, 1)
        colour = (0.5 + 0.5 * math.cos(angle), 0.5 + 0.5 * math.cos(angle + 2.1), 0.5 + 0.5 * math.cos(angle + 4.2))
        lines += [
            f'        def SphereLight "Ball{k}"',
            "        {",
            "            color3f inputs:color = ({:.4f}, {:.4f}, {:.4f})".format(*colour),
            "            float inputs:intensity = 6",
            "            float inputs:radius = 0.05",
            f"            double3 xformOp:translate = "
            f"({1.2 * math.cos(angle):.4f}, 0.7, {1.2 * math.sin(angle) - 0.5:.4f})",
            '            uniform token[] xformOpOrder = ["xformOp:translate"]',
            "        }",
        ]
    lines += ["    }", "}", ""]
    path = directory / "exterior.usda"
    path.write_text("\n".join(lines))
    return path


def frame_asset(asset: Path, directory: Path, name: str) -> Path:
    """Write `directory`/`name`.usda: `asset` as a sublayer, a camera `/Frame/Cam` on a diagonal
    (front, above, right) that sees the stage's bounds whole, and a distant light and a sphere light
    from beside and above it. Returns its path.

    Raises:
        RelightError: the asset cannot be opened or has no bounds.
    """
    stage = Usd.Stage.Open(str(asset))
    if stage is None:
        raise RelightError(f"{asset}: cannot be opened")
    up = UsdGeom.GetStageUpAxis(stage)
    box = UsdGeom.BBoxCache(Usd.TimeCode.Default(), [UsdGeom.Tokens.default_, UsdGeom.Tokens.render]).ComputeWorldBound(
        stage.GetPseudoRoot()
    )
    extent = box.ComputeAlignedRange()
    if extent.IsEmpty():
        raise RelightError(f"{asset}: nothing with bounds to frame")
    low, high = np.array(extent.GetMin()), np.array(extent.GetMax())
    centre, radius = (low + high) / 2, float(np.linalg.norm(high - low)) / 2
    up_vector = np.array([0.0, 0.0, 1.0]) if up == UsdGeom.Tokens.z else np.array([0.0, 1.0, 0.0])
    side = np.array([1.0, 0.0, 0.0])
    front = np.cross(side, up_vector)
    # 24 mm over a 36 x 27 mm aperture: the vertical half-angle is about 29 degrees.
    direction = 0.55 * side + 0.45 * up_vector + front
    direction /= np.linalg.norm(direction)
    eye = centre + direction * radius / math.sin(math.radians(27))
    # Lights from beside and above the camera, so that what the camera sees is lit.
    sun = centre + (direction + 0.6 * up_vector - 0.8 * side) * radius
    bulb = eye + (0.5 * up_vector - 0.5 * side) * radius
    matrix = _matrix(_look_at(tuple(eye), tuple(centre), tuple(up_vector)))
    sun_matrix = _matrix(_look_at(tuple(sun), tuple(centre), tuple(up_vector)))
    lines = [
        "#usda 1.0",
        "(",
        '    defaultPrim = "Frame"',
        f"    metersPerUnit = {UsdGeom.GetStageMetersPerUnit(stage):.9g}",
        f"    subLayers = [@{asset.resolve().as_posix()}@]",
        f'    upAxis = "{up}"',
        ")",
        "",
        'def Xform "Frame"',
        "{",
        '    def Camera "Cam"',
        "    {",
        f"        float2 clippingRange = ({radius * 1e-3:.6g}, {radius * 100:.6g})",
        "        float focalLength = 24",
        "        float horizontalAperture = 36",
        "        float verticalAperture = 27",
        f"        matrix4d xformOp:transform = {matrix}",
        '        uniform token[] xformOpOrder = ["xformOp:transform"]',
        "    }",
        '    def DistantLight "Sun"',
        "    {",
        "        float inputs:intensity = 1.5",
        f"        matrix4d xformOp:transform = {sun_matrix}",
        '        uniform token[] xformOpOrder = ["xformOp:transform"]',
        "    }",
        '    def SphereLight "Bulb"',
        "    {",
        "        color3f inputs:color = (1, 0.85, 0.7)",
        "        float inputs:intensity = 100",
        f"        float inputs:radius = {0.1 * radius:.6g}",
        "        double3 xformOp:translate = ({:.6g}, {:.6g}, {:.6g})".format(*bulb),
        '        uniform token[] xformOpOrder = ["xformOp:translate"]',
        "    }",
        "}",
        "",
    ]
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{name}.usda"
    path.write_text("\n".join(lines))
    return path


@dataclass(frozen=True)
class SuiteAsset:
    """One asset of the suite.

    Attributes:
        name: the table's row name.
        write: directory -> the shot's path (written there, or the committed file).
        camera: the camera prim to bake.
        bake_options: method -> extra `relight bake` arguments this shot needs (multiview's
            workspace where the stage's bounds do not suit it: a 400 m floor, a flat stage).
    """

    name: str
    write: Callable[[Path], Path]
    camera: str
    bake_options: Mapping[str, tuple[str, ...]] = field(default_factory=dict)


_PREVIEW = SCENE_DATA / "openusd_previewsurface_tests"

SUITE = (
    SuiteAsset("utah_teapot", lambda _: SCENE_DATA / "usdwg_teapot" / "shot_utah.usda", "/Shot/Cam"),
    SuiteAsset(
        "preview_instanced_material",
        lambda d: frame_asset(_PREVIEW / "testPreviewSurfaceInstancedMaterial.usda", d, "instanced_material"),
        "/Frame/Cam",
    ),
    SuiteAsset(
        "preview_opacity_threshold",
        lambda d: frame_asset(_PREVIEW / "testPreviewSurfaceOpacityThreshold.usda", d, "opacity_threshold"),
        "/Frame/Cam",
        # Flat (z = 0): the default workspace, the stage's bounds, has no depth to place cameras in.
        {"multiview": ("--box", "-1", "-1", "-2", "9.5", "2", "4")},
    ),
    SuiteAsset(
        "preview_translucent",
        lambda d: frame_asset(_PREVIEW / "testPreviewSurfaceTranslucent.usda", d, "translucent"),
        "/Frame/Cam",
    ),
    SuiteAsset(
        "exterior_teapots",
        lambda d: write_exterior_shot(d, teapots=8, sphere_lights=4),
        "/Shot/Cams/Horizon",
        {"multiview": ("--box", "-2", "-0.1", "-2.5", "2", "1.5", "3")},
    ),
)
"""Every asset of the suite (the exterior shot here with 8 teapots; `python -m tests.sky_support`
writes the production-scale one)."""
