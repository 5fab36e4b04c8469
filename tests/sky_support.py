"""An exterior shot with open sky, written at test time: instanced and point-instanced Utah teapots
(tests/data/scene/usdwg_teapot, CC0) on a floor, a distant light and coloured sphere lights, with
cameras that see the horizon (top half sky), only sky, a single teapot close up, and the inside of
a closed box.

`python -m tests.sky_support DIR [--teapots N]` writes the same shot for measurements (the issue's
production case is about a thousand teapots and sixteen sphere lights).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

TEAPOT = Path(__file__).parent / "data" / "scene" / "usdwg_teapot" / "Teapot.usd"

# Camera prim -> (position, look-at point); the stage is Y-up, metres.
CAMERAS = {
    "Horizon": ((0.0, 0.25, 2.5), (0.0, 0.25, 0.0)),  # level: sky above the horizon, floor below
    "Sky": ((0.0, 0.5, 0.0), (0.0, 10.0, 0.01)),  # straight up: nothing but sky
    "Close": ((0.35, 0.3, 0.45), (0.0, 0.1, 0.0)),  # one teapot filling the frame
    "Inside": ((3.0, 0.5, 3.0), (3.0, 0.5, 0.0)),  # inside the closed /Shot/Box
}


def _look_at(eye: tuple[float, float, float], target: tuple[float, float, float]) -> list[list[float]]:
    """USD row-vector world-from-camera matrix of a camera at `eye` looking at `target` (Y up)."""
    forward = [t - e for t, e in zip(target, eye, strict=True)]
    norm = math.sqrt(sum(f * f for f in forward))
    back = [-f / norm for f in forward]
    up = (0.0, 1.0, 0.0) if abs(back[1]) < 0.99 else (0.0, 0.0, -1.0)
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
        sphere_lights: coloured sphere lights in a ring above the teapots (plus one distant light).
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("directory", type=Path)
    parser.add_argument("--teapots", type=int, default=1000)
    parser.add_argument("--sphere-lights", type=int, default=16)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    args = parser.parse_args()
    print(write_exterior_shot(args.directory, args.teapots, args.sphere_lights, args.width, args.height))


if __name__ == "__main__":
    main()
