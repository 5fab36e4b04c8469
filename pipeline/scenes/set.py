"""A larger set for scale: a hall with a colonnade, arches, furniture and five lights of four types.

Stage in centimetres (metersPerUnit 0.01), +Y up, 640 x 480. The hall is 20 x 30 m and 8 m high:
walls with window openings on both long sides, a ceiling with a 6 x 12 m skylight, two rows of
eight columns (instanceable references to one class prototype, ~15k triangles each), fourteen
arches, ten tables with forty chairs and ten vases (two PointInstancers). About 320k triangles once
instances are expanded, but only ~20k unique ones in the layer, so it opens in well under a second.

Lights and exposure (albedos 0.35-0.7; radiance of a lit Lambertian surface = albedo / pi * E):
    Sun       DistantLight, normalize on, intensity 5 (E = 5 on a surface facing it), angle 0.53,
              through the skylight: sunlit floor (albedo 0.45, cos 0.87) ~0.62.
    Window    RectLight 200 x 400 cm in a window of the +x wall, emitting into the hall,
              intensity 10: the floor 3 m away gets E ~ 3.2 -> ~0.45.
    LampA/B   SphereLights r = 12 cm, 180 cm above two tables, intensity 450:
              E = pi L (12 / 182)^2 = 6.1 on the table top -> wood (0.40 red) ~0.78.
    WallWash  DiskLight r = 20 cm with ShapingAPI (cone 30 deg, softness 0.4, focus 2) near the
              ceiling, aimed at the far wall 10.8 m away, intensity 4000: E ~ 4.0 -> plaster ~0.77.
Checked with a Mitsuba 3 path tracer on this layer (64 spp): median pixel 0.08, 99th percentile
0.81, 0.3 % of pixels above 1.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Gf, UsdGeom, UsdLux, Vt

from pipeline.scenes import authoring
from pipeline.scenes.bundled import BundledScene, LightEdit, LightOverride
from pipeline.scenes.meshes import MeshData, box, merge, plane, revolve, transformed

NAME = "set"
CAMERA = "/World/Camera"
SUN = "/World/Lights/Sun"
WINDOW = "/World/Lights/Window"
LAMP_A = "/World/Lights/LampA"
LAMP_B = "/World/Lights/LampB"
WALL_WASH = "/World/Lights/WallWash"
PROTOTYPES = "/Prototypes"
RESOLUTION = (640, 480)

HALF_WIDTH, HALF_LENGTH, HEIGHT, WALL = 1000.0, 1500.0, 800.0, 40.0
"""Hall interior half extents along x and z, height, and wall/ceiling thickness (cm)."""
WINDOW_Z = (-900.0, -300.0, 300.0, 900.0)
WINDOW_WIDTH, WINDOW_SILL, WINDOW_HEAD = 200.0, 150.0, 550.0
SKYLIGHT_HALF = (300.0, 600.0)
COLUMN_X = (-500.0, 500.0)
COLUMN_Z = tuple(np.linspace(-1400.0, 1400.0, 8))
COLUMN_SEGMENTS = 96
ARCH_SPRING_Y = 510.0
TABLE_X = (-200.0, 200.0)
TABLE_Z = tuple(np.linspace(-1000.0, 1000.0, 5))
TABLE_TOP_Y = 77.5
LAMP_A_POSITION = (-200.0, 260.0, -500.0)
LAMP_B_POSITION = (200.0, 260.0, 500.0)
WALL_WASH_POSITION = (0.0, 700.0, -500.0)
WALL_WASH_TARGET = (0.0, 300.0, -HALF_LENGTH)
SUN_DIRECTION = (0.45, -1.0, 0.25)


def _translation(offset) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, 3] = offset
    return matrix


def _rotation_x(degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    matrix = np.eye(4)
    matrix[1:3, 1:3] = [[c, -s], [s, c]]
    return matrix


def _band(radius_from: float, height_from: float, radius_to: float, height_to: float, num_segments: int) -> MeshData:
    """A cylinder, cone or annulus band between two profile points (outside on the right of travel)."""
    return revolve(np.array([[radius_from, height_from], [radius_to, height_to]]), num_segments)


def column_mesh() -> MeshData:
    """A Tuscan-style column, 510 cm tall: plinth, torus moulding, tapered shaft, echinus, abacus."""
    segments = COLUMN_SEGMENTS
    moulding_angle = np.linspace(-np.pi / 2, np.pi / 2, 17)
    moulding = revolve(
        np.stack([30.0 + 10.0 * np.cos(moulding_angle), 40.0 + 10.0 * np.sin(moulding_angle)], -1), segments
    )
    shaft_t = np.linspace(0.0, 1.0, 48)
    shaft = revolve(np.stack([28.0 - 4.0 * shaft_t**2, 50.0 + 410.0 * shaft_t], -1), segments)
    echinus_t = np.linspace(0.0, 1.0, 17)
    echinus = revolve(
        np.stack([24.0 + 14.0 * np.sin(0.5 * np.pi * echinus_t) ** 2, 460.0 + 30.0 * echinus_t], -1), segments
    )
    return merge(
        [
            box((80.0, 30.0, 80.0), (0.0, 15.0, 0.0)),
            moulding,
            _band(30.0, 50.0, 28.0, 50.0, segments),  # ledge from the moulding in to the shaft, facing up
            shaft,
            echinus,
            box((80.0, 20.0, 80.0), (0.0, 500.0, 0.0)),
        ]
    )


def arch_mesh(
    inner_radius: float = 175.0, outer_radius: float = 225.0, half_depth: float = 30.0, num_segments: int = 64
) -> MeshData:
    """A semicircular arch in the XY plane (feet at x = +-radius, y = 0), depth along z.

    Revolved as a half ring about Y over the angles whose points then rise, and stood up by a
    +90 degree turn about X: (r sin t, h, r cos t) -> (r sin t, -r cos t, h). With the defaults its
    feet (x = +-200 at mid-thickness) land centred on capitals 400 cm apart, which hide the two end
    faces, so those are not modelled.
    """
    half_ring = (np.pi / 2, 3 * np.pi / 2)
    bands = [
        revolve(
            np.array([[outer_radius, -half_depth], [outer_radius, half_depth]]), num_segments, angle_range=half_ring
        ),  # extrados, facing out
        revolve(
            np.array([[inner_radius, half_depth], [inner_radius, -half_depth]]), num_segments, angle_range=half_ring
        ),  # intrados, facing the axis
        revolve(
            np.array([[outer_radius, half_depth], [inner_radius, half_depth]]), num_segments, angle_range=half_ring
        ),  # front face (+h)
        revolve(
            np.array([[inner_radius, -half_depth], [outer_radius, -half_depth]]), num_segments, angle_range=half_ring
        ),  # back face (-h)
    ]
    return transformed(merge(bands), _rotation_x(90.0))


def table_mesh() -> MeshData:
    """A 160 x 90 cm table, top at y = 77.5."""
    legs = [box((6.0, 72.5, 6.0), (sx * 72.0, 36.25, sz * 37.0)) for sx in (-1, 1) for sz in (-1, 1)]
    return merge([box((160.0, 5.0, 90.0), (0.0, TABLE_TOP_Y - 2.5, 0.0))] + legs)


def chair_mesh() -> MeshData:
    """A chair facing +z (its back at -z), seat at y = 45."""
    legs = [box((4.0, 45.0, 4.0), (sx * 19.0, 22.5, sz * 19.0)) for sx in (-1, 1) for sz in (-1, 1)]
    return merge([box((45.0, 4.0, 45.0), (0.0, 45.0, 0.0)), box((45.0, 50.0, 4.0), (0.0, 72.0, -20.5))] + legs)


def _vase_radius(height_fraction: np.ndarray) -> np.ndarray:
    """Outer radius (cm) of the vase at a fraction of its 40 cm height."""
    return 6.0 + 10.0 * np.sin(np.pi * (0.15 + 0.7 * height_fraction)) - 3.0 * height_fraction


def vase_mesh(wall: float = 1.0, num_segments: int = 48) -> MeshData:
    """A 40 cm vase standing on y = 0, hollow with a 1 cm wall and a rim."""
    outside_t = np.linspace(0.0, 1.0, 33)
    inside_t = np.linspace(1.0, 0.05, 32)  # down the inside to a 2 cm thick bottom
    outside = np.stack([_vase_radius(outside_t), 40.0 * outside_t], -1)
    inside = np.stack([_vase_radius(inside_t) - wall, 40.0 * inside_t], -1)
    return merge(
        [
            _band(0.0, 0.0, outside[0, 0], 0.0, num_segments),  # foot, facing down
            revolve(outside, num_segments),  # facing out
            _band(outside[-1, 0], 40.0, inside[0, 0], 40.0, num_segments),  # rim, facing up
            revolve(inside, num_segments),  # facing the axis
            _band(inside[-1, 0], inside[-1, 1], 0.0, inside[-1, 1], num_segments),  # inner bottom, facing up
        ]
    )


def _wall_with_windows(side: float) -> MeshData:
    """The long wall at x = side * HALF_WIDTH (outside it), with WINDOW_Z openings."""
    center_x = side * (HALF_WIDTH + 0.5 * WALL)
    length = 2.0 * (HALF_LENGTH + WALL)
    window_height = WINDOW_HEAD - WINDOW_SILL
    edges = np.concatenate(
        [
            [-0.5 * length],
            np.ravel([(z - 0.5 * WINDOW_WIDTH, z + 0.5 * WINDOW_WIDTH) for z in WINDOW_Z]),
            [0.5 * length],
        ]
    )
    piers = [
        box((WALL, window_height, end - start), (center_x, WINDOW_SILL + 0.5 * window_height, 0.5 * (start + end)))
        for start, end in zip(edges[::2], edges[1::2], strict=True)
    ]
    return merge(
        [
            box((WALL, WINDOW_SILL, length), (center_x, 0.5 * WINDOW_SILL, 0.0)),
            box((WALL, HEIGHT - WINDOW_HEAD, length), (center_x, 0.5 * (HEIGHT + WINDOW_HEAD), 0.0)),
        ]
        + piers
    )


def _ceiling() -> MeshData:
    """The ceiling slab above y = HEIGHT with the skylight opening in its middle."""
    sx, sz = SKYLIGHT_HALF
    full_x = 2.0 * (HALF_WIDTH + WALL)
    y = HEIGHT + 0.5 * WALL
    front_depth = HALF_LENGTH + WALL - sz
    side_width = HALF_WIDTH + WALL - sx
    return merge(
        [
            box((full_x, WALL, front_depth), (0.0, y, sz + 0.5 * front_depth)),
            box((full_x, WALL, front_depth), (0.0, y, -sz - 0.5 * front_depth)),
            box((side_width, WALL, 2.0 * sz), (sx + 0.5 * side_width, y, 0.0)),
            box((side_width, WALL, 2.0 * sz), (-sx - 0.5 * side_width, y, 0.0)),
        ]
    )


def _define_materials(stage) -> dict:
    specs = {
        "Stone": dict(diffuseColor=(0.45, 0.42, 0.38), roughness=0.6),
        "Plaster": dict(diffuseColor=(0.60, 0.58, 0.55), roughness=0.9),
        "Marble": dict(diffuseColor=(0.70, 0.68, 0.64), roughness=0.25),
        "Wood": dict(diffuseColor=(0.40, 0.24, 0.12), roughness=0.45),
        "Ceramic": dict(
            diffuseColor=(0.08, 0.20, 0.35),
            useSpecularWorkflow=1,
            specularColor=(0.04, 0.04, 0.04),
            roughness=0.3,
            clearcoat=1.0,
            clearcoatRoughness=0.05,
        ),
    }
    return {name: authoring.define_preview_material(stage, name, **inputs)[0] for name, inputs in specs.items()}


def _define_room(stage, materials: dict) -> None:
    room = f"{authoring.GEOMETRY}/Room"
    parts = {
        "Floor": (plane(2.0 * HALF_WIDTH, 2.0 * HALF_LENGTH, st_repeat=10.0), "Stone"),
        "WallEast": (_wall_with_windows(1.0), "Plaster"),
        "WallWest": (_wall_with_windows(-1.0), "Plaster"),
        "WallNorth": (
            box((2.0 * (HALF_WIDTH + WALL), HEIGHT, WALL), (0.0, 0.5 * HEIGHT, -HALF_LENGTH - 0.5 * WALL)),
            "Plaster",
        ),
        "WallSouth": (
            box((2.0 * (HALF_WIDTH + WALL), HEIGHT, WALL), (0.0, 0.5 * HEIGHT, HALF_LENGTH + 0.5 * WALL)),
            "Plaster",
        ),
        "Ceiling": (_ceiling(), "Plaster"),
    }
    for name, (mesh, material) in parts.items():
        authoring.bind_material(authoring.define_mesh(stage, f"{room}/{name}", mesh).GetPrim(), materials[material])


def _define_columns(stage, materials: dict) -> int:
    """One class prototype, referenced by instanceable prims; returns the number of columns."""
    stage.CreateClassPrim(PROTOTYPES)
    UsdGeom.Xform.Define(stage, f"{PROTOTYPES}/Column")
    authoring.define_mesh(stage, f"{PROTOTYPES}/Column/Shape", column_mesh())
    positions = [(x, 0.0, z) for x in COLUMN_X for z in COLUMN_Z]
    for index, position in enumerate(positions):
        column = UsdGeom.Xform.Define(stage, f"{authoring.GEOMETRY}/Columns/Column_{index:02d}")
        column.GetPrim().GetReferences().AddInternalReference(f"{PROTOTYPES}/Column")
        column.GetPrim().SetInstanceable(True)
        authoring.place(column, position)
        authoring.bind_material(column.GetPrim(), materials["Marble"])
    return len(positions)


def _yaw_quaternions(degrees: np.ndarray) -> Vt.QuathArray:
    half = np.radians(np.asarray(degrees, np.float64)) / 2.0
    return Vt.QuathArray([Gf.Quath(float(np.cos(h)), Gf.Vec3h(0.0, float(np.sin(h)), 0.0)) for h in half])


def _define_point_instancer(
    stage,
    path: str,
    prototypes: dict[str, tuple[MeshData, str]],
    materials: dict,
    proto_indices: np.ndarray,
    positions: np.ndarray,
    yaw_degrees: np.ndarray,
) -> None:
    """A PointInstancer with mesh prototypes under <path>/Prototypes (each bound to its material)."""
    instancer = UsdGeom.PointInstancer.Define(stage, path)
    targets = []
    for name, (mesh, material) in prototypes.items():
        prototype = authoring.define_mesh(stage, f"{path}/Prototypes/{name}", mesh)
        authoring.bind_material(prototype.GetPrim(), materials[material])
        targets.append(prototype.GetPath())
    instancer.CreatePrototypesRel().SetTargets(targets)
    instancer.CreateProtoIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(proto_indices, np.int32)))
    instancer.CreatePositionsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(positions, np.float32)))
    instancer.CreateOrientationsAttr(_yaw_quaternions(yaw_degrees))


def _define_instancers(stage, materials: dict) -> None:
    # Arches between neighbouring columns of each row, turned to span along z.
    arch_z = 0.5 * (np.asarray(COLUMN_Z[:-1]) + np.asarray(COLUMN_Z[1:]))
    arch_positions = np.array([(x, ARCH_SPRING_Y, z) for x in COLUMN_X for z in arch_z])
    _define_point_instancer(
        stage,
        f"{authoring.GEOMETRY}/Arcade",
        {"Arch": (arch_mesh(), "Marble")},
        materials,
        np.zeros(len(arch_positions)),
        arch_positions,
        np.full(len(arch_positions), 90.0),
    )

    # Tables, four chairs around each facing it, a vase on each.
    tables = np.array([(x, 0.0, z) for x in TABLE_X for z in TABLE_Z])
    chair_offsets = np.array([(-40.0, 0.0, -65.0), (40.0, 0.0, -65.0), (-40.0, 0.0, 65.0), (40.0, 0.0, 65.0)])
    chairs = (tables[:, None, :] + chair_offsets[None]).reshape(-1, 3)
    chair_yaw = np.tile([0.0, 0.0, 180.0, 180.0], len(tables))  # chairs face +z; far side turned round
    vases = tables + (0.0, TABLE_TOP_Y, 0.0)
    _define_point_instancer(
        stage,
        f"{authoring.GEOMETRY}/Furniture",
        {"Table": (table_mesh(), "Wood"), "Chair": (chair_mesh(), "Wood"), "Vase": (vase_mesh(), "Ceramic")},
        materials,
        np.concatenate([np.zeros(len(tables)), np.ones(len(chairs)), np.full(len(vases), 2)]),
        np.concatenate([tables, chairs, vases]),
        np.concatenate([np.zeros(len(tables)), chair_yaw, np.zeros(len(vases))]),
    )


def _define_lights(stage) -> None:
    sun = UsdLux.DistantLight.Define(stage, SUN)
    sun.CreateAngleAttr(0.53)
    authoring.set_light(sun.LightAPI(), intensity=5.0, color=(1.0, 0.95, 0.85), normalize=True)
    authoring.place(sun, (0.0, 0.0, 0.0), authoring.aim_rotation_xyz(SUN_DIRECTION))

    window = UsdLux.RectLight.Define(stage, WINDOW)
    window.CreateWidthAttr(WINDOW_WIDTH)
    window.CreateHeightAttr(WINDOW_HEAD - WINDOW_SILL)
    authoring.set_light(window.LightAPI(), intensity=10.0, color=(0.8, 0.9, 1.0))
    window_position = (HALF_WIDTH + 0.5 * WALL, 0.5 * (WINDOW_SILL + WINDOW_HEAD), WINDOW_Z[2])
    authoring.place_aimed(window, window_position, np.subtract(window_position, (1.0, 0.0, 0.0)))

    for path, position in ((LAMP_A, LAMP_A_POSITION), (LAMP_B, LAMP_B_POSITION)):
        lamp = UsdLux.SphereLight.Define(stage, path)
        lamp.CreateRadiusAttr(12.0)
        authoring.set_light(lamp.LightAPI(), intensity=450.0, color=(1.0, 0.85, 0.65))
        authoring.place(lamp, position)

    wash = UsdLux.DiskLight.Define(stage, WALL_WASH)
    wash.CreateRadiusAttr(20.0)
    authoring.set_light(wash.LightAPI(), intensity=4000.0)
    authoring.shape_spot(wash.GetPrim(), cone_angle=30.0, softness=0.4, focus=2.0)
    authoring.place_aimed(wash, WALL_WASH_POSITION, WALL_WASH_TARGET)


def write(directory: Path) -> Path:
    """Write DIR/set.usda and return its path."""
    stage = authoring.create_stage(0.01, "Set for scale: a colonnaded hall with furniture (centimetres).")
    materials = _define_materials(stage)
    _define_room(stage, materials)
    _define_columns(stage, materials)
    _define_instancers(stage, materials)
    _define_lights(stage)
    camera = authoring.define_camera(
        stage,
        CAMERA,
        (0.0, 170.0, 1400.0),
        (0.0, 250.0, -HALF_LENGTH),
        focal_length_mm=24.0,
        aperture_mm=(36.0, 27.0),
        clipping_range=(1.0, 1.0e5),
    )
    authoring.define_render_settings(stage, camera, RESOLUTION)
    return authoring.save_stage(stage, Path(directory) / f"{NAME}.usda")


LIGHT_EDITS = (
    LightEdit(
        "move",
        "move lamp A to the other end of its table row",
        (LightOverride(LAMP_A, {"xformOp:translate": ("double3", Gf.Vec3d(-200.0, 260.0, 1000.0))}),),
    ),
    LightEdit(
        "reaim_spot",
        "re-aim the wall wash at the east wall's windows",
        (
            LightOverride(
                WALL_WASH,
                {
                    "xformOp:rotateXYZ": (
                        "float3",
                        authoring.aim_rotation_xyz(np.subtract((HALF_WIDTH, 300.0, 0.0), WALL_WASH_POSITION)),
                    )
                },
            ),
        ),
    ),
    LightEdit(
        "colour_shaping",
        "late-afternoon sun: lower, warmer; wall wash narrower and harder",
        (
            LightOverride(
                SUN,
                {
                    "xformOp:rotateXYZ": ("float3", authoring.aim_rotation_xyz((0.9, -0.6, 0.2))),
                    "inputs:color": ("color3f", Gf.Vec3f(1.0, 0.7, 0.45)),
                },
            ),
            LightOverride(
                WALL_WASH,
                {"inputs:shaping:cone:angle": ("float", 15.0), "inputs:shaping:cone:softness": ("float", 0.05)},
            ),
        ),
    ),
)

SCENE = BundledScene(
    name=NAME,
    camera=CAMERA,
    description="hall with a colonnade, arches and furniture (~320k triangles via instancing); "
    "sun, window rect, two sphere lamps, disk spot",
    write=write,
    light_edits=LIGHT_EDITS,
)
