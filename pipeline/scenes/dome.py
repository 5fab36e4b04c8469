"""The glossy scene under a textured DomeLight: environment lighting for the cuts method (Cheslack-Postava et al. 2008).

DIR/dome.usda sublayers DIR/glossy.usda (written beside it, `pipeline.scenes.glossy`), deactivates
its Key and Spot lights and adds /World/Lights/Dome, a DomeLight with a generated lat-long HDR
texture (DIR/textures/dome_sky.exr, float32 linear RGB, row 0 = zenith):

    sky      blue-to-white gradient over the upper hemisphere, radiance ~0.35-0.6
    ground   a dim brown below the horizon, radiance 0.08
    sun      a disk of 6 degrees radius at elevation 40 degrees, radiance 40 (a soft edge of 2
             degrees): the "high-frequency" light that the illumination cut must refine
    window   a warm rectangle low on the opposite side (radiance 4), for a second shadow

Intensity 1 (radiance = texture), camera, materials and geometry are the glossy scene's.

`GLOSSY_DOME` ('glossy+dome') is the same dome added to the glossy shot by a lights layer instead
(DIR/glossy.lights.dome.usda, `write_lights_layer`): the Key and Spot stay, the dome at half
intensity fills in; a cache baked from glossy.usda relights it with `--lights`.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdLux

from pipeline.scenes import authoring, glossy
from pipeline.scenes.bundled import BundledScene, LayeredScene, LightEdit, LightOverride
from relight_torch.io.atomic import atomic_path, write_text_atomic
from relight_torch.io.exr import write_rgb_exr

NAME = "dome"
DOME = "/World/Lights/Dome"
TEXTURE = "textures/dome_sky.exr"
TEXTURE_SIZE = (128, 256)
SUN_DIRECTION = (0.55, 0.643, 0.533)
"""Unit world direction towards the sun (elevation 40 degrees, in front-right of the camera's view)."""
LIGHTS_LAYER = f"{glossy.NAME}.lights.dome.usda"
FILL_INTENSITY = 0.5
"""The dome's intensity beside the glossy shot's own lights (`write_lights_layer`)."""


def sky_texture(height: int = TEXTURE_SIZE[0], width: int = TEXTURE_SIZE[1]) -> np.ndarray:
    """(H, W, 3) float32 lat-long radiance (row 0 = +Y pole; `relight_torch.lights.dome` convention)."""
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(width) + 0.5) / width
    theta = v[:, None] * math.pi
    longitude = (0.5 - u[None, :]) * 2.0 * math.pi
    direction = np.stack(
        np.broadcast_arrays(np.sin(theta) * np.sin(longitude), np.cos(theta), np.sin(theta) * np.cos(longitude)),
        axis=-1,
    )
    up = direction[..., 1:2]
    zenith, horizon = np.array([0.25, 0.4, 0.8]), np.array([0.6, 0.62, 0.65])
    sky = horizon + (zenith - horizon) * np.clip(up, 0.0, 1.0) ** 0.5
    image = np.where(up > 0, sky, np.array([0.08, 0.06, 0.04]))
    sun_angle = np.degrees(np.arccos(np.clip(direction @ np.asarray(SUN_DIRECTION), -1.0, 1.0)))
    sun = np.clip((8.0 - sun_angle) / 2.0, 0.0, 1.0)[..., None]
    image = image + sun * np.array([40.0, 38.0, 34.0])
    window = (np.abs(direction[..., 0] + 0.8) < 0.25) & (up[..., 0] > 0.05) & (up[..., 0] < 0.35)
    image = image + window[..., None] * np.array([4.0, 3.0, 2.0])
    return image.astype(np.float32)


def _define_dome(stage: Usd.Stage, intensity: float) -> None:
    """Define /World/Lights/Dome on `stage`: the lat-long sky (DIR/textures/dome_sky.exr) at `intensity`."""
    dome = UsdLux.DomeLight.Define(stage, DOME)
    authoring.set_light(dome.LightAPI(), intensity=intensity)
    dome.CreateTextureFileAttr(f"./{TEXTURE}")
    dome.CreateTextureFormatAttr(UsdLux.Tokens.latlong)
    authoring.place(dome, (0.0, 0.0, 0.0), rotate_xyz=(0.0, 0.0, 0.0))


def write_lights_layer(directory: Path) -> Path:
    """Write DIR/glossy.lights.dome.usda, a lights layer adding the dome to the glossy shot (its
    Key and Spot kept), with the glossy scene and the sky texture beside it; return the layer's path."""
    directory = Path(directory)
    glossy.write(directory)
    write_rgb_exr(directory / TEXTURE, sky_texture())
    stage = Usd.Stage.CreateInMemory()
    stage.GetRootLayer().documentation = f"Lights layer over {glossy.NAME}.usda: {GLOSSY_DOME_DESCRIPTION}."
    _define_dome(stage, FILL_INTENSITY)
    for ancestor in (authoring.WORLD, authoring.LIGHTS):  # `over`s: the shot defines them
        stage.GetPrimAtPath(ancestor).SetSpecifier(Sdf.SpecifierOver)
    path = directory / LIGHTS_LAYER
    write_text_atomic(path, stage.GetRootLayer().ExportToString())
    return path


def write(directory: Path) -> Path:
    """Write DIR/dome.usda (and the glossy scene and textures it uses); return the layer's path."""
    directory = Path(directory)
    glossy_layer = glossy.write(directory)
    write_rgb_exr(directory / TEXTURE, sky_texture())
    stage = authoring.create_stage(0.01, "The glossy scene under a textured dome light (centimetres).")
    for light in (glossy.KEY, glossy.SPOT):
        stage.OverridePrim(light).SetActive(False)
    _define_dome(stage, 1.0)
    stage.SetMetadata("renderSettingsPrimPath", authoring.RENDER_SETTINGS)
    # The sublayer is added to a detached copy of the layer: an in-memory stage cannot resolve
    # the relative path (USD would warn), the file written beside glossy.usda can.
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.ImportFromString(stage.GetRootLayer().ExportToString())
    layer.subLayerPaths.append(f"./{glossy_layer.name}")
    path = directory / f"{NAME}.usda"
    with atomic_path(path) as temp:
        if not layer.Export(str(temp)):
            raise OSError(f"could not write USD layer {temp}")
    return path


ROTATE = LightEdit(
    "rotate",
    "turn the dome 120 degrees about +Y (the sun moves round to the left)",
    (LightOverride(DOME, {"xformOp:rotateXYZ": ("float3", Gf.Vec3f(0.0, 120.0, 0.0))}),),
)
LIGHT_EDITS = (
    ROTATE,
    LightEdit(
        "warm",
        "warm the dome's colour and raise its exposure",
        (
            LightOverride(
                DOME, {"inputs:color": ("color3f", Gf.Vec3f(1.0, 0.8, 0.6)), "inputs:exposure": ("float", 0.5)}
            ),
        ),
    ),
    LightEdit("dim", "halve the dome's intensity", (LightOverride(DOME, {"inputs:intensity": ("float", 0.5)}),)),
)

SCENE = BundledScene(
    name=NAME,
    camera=glossy.CAMERA,
    description="the glossy scene lit only by a textured dome (generated lat-long EXR sky with a sun)",
    write=write,
    light_edits=LIGHT_EDITS,
)

GLOSSY_DOME_DESCRIPTION = "the glossy shot with the textured dome added at half intensity, its own lights kept"
GLOSSY_DOME = LayeredScene(
    name=f"{glossy.NAME}+{NAME}",
    base=glossy.NAME,
    description=GLOSSY_DOME_DESCRIPTION,
    write_layer=write_lights_layer,
    light_edits=(*glossy.LIGHT_EDITS, ROTATE),
)
