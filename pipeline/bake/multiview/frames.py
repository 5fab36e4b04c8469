"""Rendering a multiview cache from a camera prim, over time codes (`relight render CACHE --camera PRIM`).

The camera is read from the shot with the lights layer composed over it, so a camera authored in
the lights layer works as well as one in the shot; each time code reads the camera there (an
animated camera is a camera path). The lights are the shot's at the baked time, with the layer's
edits. Per frame: primary rays (`view.view_points`), correspondence map and hole filling
(`MultiviewRelighter.set_view`); with `fill_holes`, the pixels of the large holes are baked on
demand (`holes.hole_patch`, the shot loaded once) and the view is set again with them.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from pxr import UsdGeom

from pipeline.bake.multiview.holes import hole_patch
from pipeline.bake.multiview.view import view_points
from pipeline.errors import RelightError
from pipeline.scene.camera import read_camera
from pipeline.scene.load import load_scene
from pipeline.scene.types import Camera, Scene
from relight_torch.io.exr import write_rgb_exr
from relight_torch.io.preview import write_png
from relight_torch.multiview.correspondence import ViewPoints
from relight_torch.multiview.holes import HoleReport
from relight_torch.multiview.relighter import MultiviewRelighter
from relight_torch.progressive import STRIDES
from relight_torch.stage import open_stage, time_code


@dataclass(frozen=True)
class Frame:
    """One rendered view: the image (H, W, 3), its hole report, and the holes left after any patch."""

    image: np.ndarray
    report: HoleReport
    patched_pixels: int


def read_view_camera(
    source: str, lights_layer: str | os.PathLike | None, path: str, time: float | None, width: int, height: int
) -> Camera:
    """Camera prim `path` of the shot (with `lights_layer` over it) at `time`.

    Raises:
        RelightError: no camera prim there.
    """
    stage = open_stage(source, lights_layer)
    prim = stage.GetPrimAtPath(path)
    if not prim or not prim.IsA(UsdGeom.Camera):
        raise RelightError(f"camera {path} not found in {source}" + (f" or {lights_layer}" if lights_layer else ""))
    return read_camera(UsdGeom.Camera(prim), time_code(stage, time), width, height)


class FrameRenderer:
    """Renders frames of a multiview relighter, loading the shot only when a hole needs baking."""

    def __init__(
        self, relighter: MultiviewRelighter, lights_layer: str | os.PathLike | None = None, fill_holes: bool = False
    ):
        self.relighter = relighter
        self.lights_layer = lights_layer
        self.fill_holes = fill_holes
        self._scene: Scene | None = None
        """The shot, loaded for the first hole patch and kept (its BVH: `shared_tracer`)."""

    def render(self, camera: Camera) -> Frame:
        relighter = self.relighter
        view = camera_view(relighter, camera)
        report = relighter.set_view(view, exposure_scale=camera.exposure_scale)
        patched = 0
        if self.fill_holes and report.num_large_holes:
            if self._scene is None:
                description = relighter.description
                self._scene = load_scene(
                    description.source, time=description.parameters.get("time"), lights_layer=self.lights_layer
                )
            pixels = report.large_pixel_index.cpu().numpy()
            patch = hole_patch(self._scene, camera, relighter.supersampling, pixels)
            relighter.set_view(view, patch=patch, exposure_scale=camera.exposure_scale)
            patched = patch.num_samples
        return Frame(relighter.render().cpu().numpy(), report, patched)


def camera_view(relighter: MultiviewRelighter, camera: Camera) -> ViewPoints:
    """The surfaces `camera` sees, at the relighter's supersampling (`view.view_points`)."""
    return view_points(
        relighter.caster, relighter.occluder_objects, camera, relighter.supersampling, relighter.corner_normals
    )


def set_camera(relighter: MultiviewRelighter, camera: Camera) -> HoleReport:
    """Move the relighter to `camera`: its primary rays and correspondence map
    (`MultiviewRelighter.set_view`); the frame is the relighter's `render()` after."""
    return relighter.set_view(camera_view(relighter, camera), exposure_scale=camera.exposure_scale)


def coarse_camera(camera: Camera, stride: int) -> Camera:
    """`camera` with an image `stride` times smaller on each side (rounded up), the same frustum."""
    return dataclasses.replace(camera, width=-(-camera.width // stride), height=-(-camera.height // stride))


def camera_move_frames(
    relighter: MultiviewRelighter, camera: Camera, strides: Sequence[int] = STRIDES
) -> Iterator[tuple[int | None, torch.Tensor]]:
    """A camera move's frames, coarse to exact, as (stride or None, (H, W, 3) image): per stride
    the new view traced, matched and relit at one pixel per stride x stride (`coarse_camera`),
    brought to the camera's size bilinearly; then the view itself, whose frame is the one
    `set_camera` then `render()` make (the relighter is left at that view). The light cached at
    the caching samples serves every level: a coarse level's work is its pixels'."""
    for stride in strides:
        set_camera(relighter, coarse_camera(camera, stride))
        image = relighter.render().permute(2, 0, 1).unsqueeze(0)
        # Each coarse pixel covers stride x stride pixels: sized up, then cut to the camera's size.
        size = (image.shape[2] * stride, image.shape[3] * stride)
        full = torch.nn.functional.interpolate(image, size=size, mode="bilinear", align_corners=False)
        yield stride, full[0, :, : camera.height, : camera.width].permute(1, 2, 0)
    set_camera(relighter, camera)
    yield None, relighter.render()


def frame_path(out: str | os.PathLike, time: float | None, num_frames: int) -> Path:
    """OUT itself for one frame; OUT with '.<time>' before its suffix for several (e.g. out.0012.exr)."""
    out = Path(out)
    if num_frames == 1 or time is None:
        return out
    label = f"{int(time):04d}" if float(time).is_integer() else f"{time:g}"
    return out.with_name(f"{out.stem}.{label}{out.suffix}")


def render_frames(
    relighter: MultiviewRelighter,
    camera_path: str,
    times: list[float | None],
    out: str,
    width: int,
    height: int,
    lights_layer: str | None = None,
    png: str | None = None,
    fill_holes: bool = False,
    aov_layers: Callable[[MultiviewRelighter], dict[str, np.ndarray]] | None = None,
) -> list[Frame]:
    """Render `camera_path` at each time code into OUT (per-frame names when several); print a line per frame."""
    renderer = FrameRenderer(relighter, lights_layer, fill_holes)
    frames = []
    for time in times:
        camera = read_view_camera(relighter.description.source, lights_layer, camera_path, time, width, height)
        frame = renderer.render(camera)
        path = frame_path(out, time, len(times))
        write_rgb_exr(path, frame.image, aov_layers(relighter) if aov_layers else None)
        if png:
            write_png(frame_path(png, time, len(times)), frame.image)
        report = frame.report
        print(
            f"{path}: {camera_path} at {width}x{height}, {len(relighter.lights)} lights; holes "
            f"{100 * report.hole_fraction_before:.2f}% of covered pixels, {100 * report.hole_fraction_after:.2f}% "
            f"after filling, {report.num_large_holes} large"
            + (f" ({frame.patched_pixels} sub-samples baked on demand)" if frame.patched_pixels else "")
        )
        frames.append(frame)
    return frames
