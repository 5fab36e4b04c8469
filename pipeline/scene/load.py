"""The entry point of the USD walk: a shot (plus optional light edits) to a `Scene`."""

from __future__ import annotations

from pathlib import Path

from pxr import Usd, UsdGeom

from pipeline.errors import RelightError, warn
from pipeline.scene.camera import read_cameras
from pipeline.scene.geometry import read_geometry
from pipeline.scene.lights import read_lights
from pipeline.scene.materials import MaterialLibrary
from pipeline.scene.types import Camera, Scene
from relight_torch.stage import check_composition, defining_layer, open_stage, time_code


def read_scene(
    stage: Usd.Stage, source: str, *, time: float | None = None, width: int | None = None, height: int | None = None
) -> Scene:
    """Everything the renderers need from an open stage; the geometry may be empty.

    Args:
        stage: the composed stage (see `open_stage`).
        source: path of the shot, recorded as `Scene.source`.
        time: USD time code to read, None for the stage's first frame (see `time_code`).
        width, height: image size overrides in pixels (else the render settings, else 640x480).
    """
    code = time_code(stage, time)
    warnings: list[str] = []
    library = MaterialLibrary(stage, warnings, code)
    cameras = read_cameras(stage, code, width, height, warnings)
    # Subdivision surfaces are refined for the cameras at this image size (pipeline.scene.dicing).
    geometry, objects = read_geometry(stage, code, library, warnings, cameras)
    lights = read_lights(stage, code, warnings)
    return Scene(
        source=source,
        geometry=geometry,
        objects=objects,
        materials=library.materials,
        lights=lights,
        cameras=cameras,
        meters_per_unit=float(UsdGeom.GetStageMetersPerUnit(stage)),
        up_axis=str(UsdGeom.GetStageUpAxis(stage)),
        warnings=warnings,
        read_size=(width, height),
    )


def load_scene(
    path: str | Path,
    *,
    time: float | None = None,
    lights_layer: str | Path | None = None,
    materials_layer: str | Path | None = None,
    width: int | None = None,
    height: int | None = None,
) -> Scene:
    """Open a shot and read it into a `Scene`.

    Args:
        path: the shot (.usd, .usda, .usdc, .usdz).
        time: USD time code to read, None for the stage's first frame (see `time_code`).
        lights_layer: a USD layer of light edits composed as the strongest sublayer, or None.
        materials_layer: a USD layer of material edits composed below it, or None.
        width, height: image size overrides in pixels.

    Raises:
        RelightError: the files cannot be opened, or the stage has nothing to render. A stage
            without lights only warns (lights may come from a later `--lights` layer).
    """
    source = str(Path(path).resolve())
    stage = open_stage(path, lights_layer, materials_layer)
    material_warnings = check_composition(stage, path)
    try:
        scene = read_scene(stage, source, time=time, width=width, height=height)
    except RelightError as error:
        if Path(path).name in str(error):
            raise
        raise RelightError(f"{defining_layer(stage, str(error), path)}: {error}") from None
    for message in material_warnings:
        warn(message, scene.warnings)
    if scene.geometry.num_triangles == 0:
        skipped = f" ({len(scene.warnings)} warnings; first: {scene.warnings[0]})" if scene.warnings else ""
        raise RelightError(f"stage {path} has no renderable meshes or gprims{skipped}")
    if not scene.lights:
        warn(f"stage {path} has no lights", scene.warnings)
    return scene


def find_camera(scene: Scene, path: str) -> Camera:
    """The scene's camera at prim path `path`.

    Raises:
        RelightError: no camera there; the message lists the cameras that exist.
    """
    if path in scene.cameras:
        return scene.cameras[path]
    available = ", ".join(sorted(scene.cameras)) or "none"
    raise RelightError(f"camera {path} not found in {scene.source}; cameras: {available}")
