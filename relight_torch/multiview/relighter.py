"""Relighting a multiview cache from any camera: correspondence map, then the direct Relighter.

For each new view (`set_view`), the caller's visible points (`ViewPoints`) are matched to caching
camera samples (`correspondence_map`, eq. 5), small holes are filled (`fill_small_holes`), and a
GBuffer is assembled: the new view's own positions, geometric normals and depths with the chosen
samples' material parameters and shading frames, bilinearly resampled (`resample`). Where the
material does not perturb its normal, the view's own smooth normal replaces the cached one (the
frame re-orthonormalised around it): a cached normal is the one at the caching pixel's centre,
which on a curved surface seen by a coarser caching camera is off by up to a caching pixel and
shifts highlights. The direct `Relighter` then shades it with the usual lights and shadows; there
is no second shading path. Lights persist across views; a view change rebuilds the per-light
transport (the shading points moved), a light edit at a fixed view re-renders only what it
touches, as for a single-view cache.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import torch

from relight_torch.cache.layer import CacheDescription, read_cache_layer
from relight_torch.cache.load import check_inputs, load_npy
from relight_torch.errors import RelightError
from relight_torch.gbuffer import GBuffer
from relight_torch.lights.light import Light
from relight_torch.lights.linking import decode_paths
from relight_torch.multiview.correspondence import ViewPoints, correspondence_map
from relight_torch.multiview.holes import HoleReport, fill_small_holes
from relight_torch.multiview.load import load_camera_table, load_view_gbuffers
from relight_torch.multiview.resample import bilinear_samples
from relight_torch.multiview.views import CachingViews, concat_gbuffers, gather_gbuffer
from relight_torch.relighter import Relighter, RelightSettings, embree_visibility, shot_lights
from relight_torch.visibility.embree import EmbreeCaster


def view_gbuffer(views: CachingViews, view: ViewPoints, patch: GBuffer | None = None,
                 normal_mapped: torch.Tensor | None = None) -> tuple[GBuffer, HoleReport]:
    """The new view's GBuffer from the caching cameras' samples (see the module docstring).

    Args:
        views: the caching cameras, on the view's device.
        view: the new view's visible points.
        patch: samples baked on demand for (some of) the large holes' pixels, or None: those
            pixels then stay black.
        normal_mapped: (num_materials,) bool, materials whose cached normals are kept; None keeps
            every cached normal (and so does a view without `shading_normal`).

    Returns:
        (the GBuffer over the view's (H, W) sub-sample image, the hole report).
    """
    correspondence = correspondence_map(views, view.position, view.geometric_normal, view.object_id)
    rows, report = fill_small_holes(view, correspondence.pool_row, views.pool)
    keep = torch.nonzero(rows >= 0).squeeze(-1)
    # Filled holes are resampled at their neighbour's pixel centre: that sample alone.
    matched = (correspondence.pool_row[keep] >= 0)[:, None]
    row = rows[keep]
    chosen = bilinear_samples(views, torch.where(matched[:, 0], correspondence.view[keep], views.pool_view[row]),
                              torch.where(matched, correspondence.pixel[keep], views.pool_pixel[row]), row,
                              view.object_id[keep], view.geometric_normal[keep])
    gbuffer = GBuffer(image_size=view.image_size, pixel_index=view.pixel_index[keep], position=view.position[keep],
                      geometric_normal=view.geometric_normal[keep], depth=view.depth[keep],
                      camera_position=view.camera_position, **chosen._asdict())
    if view.shading_normal is not None and normal_mapped is not None:
        gbuffer = _smooth_frames(gbuffer, view.shading_normal[keep], ~normal_mapped[gbuffer.material_id.long()])
    if patch is not None:
        if patch.image_size != view.image_size:
            raise ValueError(f"hole patch is for a {patch.image_size} image, the view is {view.image_size}")
        taken = torch.zeros(view.image_size[0] * view.image_size[1], dtype=torch.bool, device=view.position.device)
        taken[gbuffer.pixel_index] = True
        fresh = gather_gbuffer(patch, torch.nonzero(~taken[patch.pixel_index]).squeeze(-1))
        gbuffer = concat_gbuffers([gbuffer, fresh], view.image_size,
                                  torch.cat([gbuffer.pixel_index, fresh.pixel_index]), view.camera_position)
    return gbuffer, report


def _smooth_frames(gbuffer: GBuffer, smooth: torch.Tensor, use: torch.Tensor) -> GBuffer:
    """`gbuffer` with the normal replaced by `smooth` (N, 3) where `use` (N,), tangent frame rebuilt."""
    normal = torch.where(use[:, None], smooth.to(gbuffer.normal.dtype), gbuffer.normal)
    tangent = gbuffer.tangent - normal * (gbuffer.tangent * normal).sum(-1, keepdim=True)
    tangent = torch.nn.functional.normalize(tangent, dim=-1)
    return dataclasses.replace(gbuffer, normal=normal, tangent=tangent, bitangent=torch.cross(normal, tangent, dim=-1))


class MultiviewRelighter:
    """Direct relighting of a multiview cache from a camera that moves.

    Args:
        views: the caching cameras and their deep framebuffers (device of every computation).
        visibility: shadow queries for the direct Relighter.
        supersampling: s x s sub-samples per pixel of the new views.
        exposure_scale: the cache's camera exposure scale (`set_view` may change it).
        settings, object_paths: as `Relighter`.

    Attributes:
        caster: Embree over the cache's occluders, for the new views' primary rays.
        occluder_objects: (T,) object id of each occluder triangle (the object of a primary hit).
        corner_normals: (T, 3, 3) smooth normals of the occluders' corners, or None.
        normal_mapped: (num_materials,) bool tensor, materials whose cached normals are kept, or None.
        description: the cache layer's description when opened with `open_multiview_relighter`.
        report: the last view's `HoleReport`.
    """

    def __init__(self, views: CachingViews, visibility, supersampling: int = 1, exposure_scale: float = 1.0,
                 settings: RelightSettings = RelightSettings(), object_paths: list[str] | None = None,
                 caster: EmbreeCaster | None = None, occluder_objects: np.ndarray | None = None,
                 corner_normals: np.ndarray | None = None, normal_mapped: torch.Tensor | None = None):
        self.views = views
        self.visibility = visibility
        self.supersampling = supersampling
        self.exposure_scale = exposure_scale
        self.settings = settings
        self.object_paths = object_paths
        self.caster = caster
        self.occluder_objects = occluder_objects
        self.corner_normals = corner_normals
        self.normal_mapped = normal_mapped
        self.description: CacheDescription | None = None
        self.report: HoleReport | None = None
        self._lights: dict[str, Light] = {}
        self._relighter: Relighter | None = None

    @property
    def relighter(self) -> Relighter:
        """The direct Relighter of the current view."""
        if self._relighter is None:
            raise RelightError("multiview relighter: no view set (call set_view with the new camera's points)")
        return self._relighter

    @property
    def lights(self) -> list[Light]:
        return list(self._lights.values())

    def set_lights(self, lights: list[Light]) -> None:
        self._lights = {light.path: light for light in lights}
        if self._relighter is not None:
            self._relighter.set_lights(lights)

    def set_light(self, light: Light) -> None:
        self._lights[light.path] = light
        if self._relighter is not None:
            self._relighter.set_light(light)

    def remove_light(self, path: str) -> None:
        self._lights.pop(path, None)
        if self._relighter is not None:
            self._relighter.remove_light(path)

    def set_view(self, view: ViewPoints, patch: GBuffer | None = None,
                 exposure_scale: float | None = None) -> HoleReport:
        """Move to a new view: correspondence map, hole filling, and a fresh Relighter over it."""
        if exposure_scale is not None:
            self.exposure_scale = exposure_scale
        gbuffer, self.report = view_gbuffer(self.views, view.to(self.views.device), patch, self.normal_mapped)
        self._relighter = Relighter(gbuffer, self.visibility, self.supersampling, self.exposure_scale,
                                    self.settings, self.object_paths)
        self._relighter.set_lights(self.lights)
        return self.report

    def render(self) -> torch.Tensor:
        """(H, W, 3) linear image of the current view."""
        return self.relighter.render()

    def light_image(self, path: str) -> torch.Tensor:
        return self.relighter.light_image(path)

    def light_group_images(self) -> dict[str, torch.Tensor]:
        return self.relighter.light_group_images()

    def emission_image(self) -> torch.Tensor:
        return self.relighter.emission_image()


def open_multiview_relighter(path: str | os.PathLike, device: str | torch.device = "cpu", shadows: str = "embree",
                             lights_layer: str | os.PathLike | None = None,
                             settings: RelightSettings = RelightSettings()) -> MultiviewRelighter:
    """A MultiviewRelighter for a 'multiview' cache layer, with the shot's lights (and `lights_layer`'s).

    No view is set: give it one with `set_view` (`pipeline.bake.multiview.view.view_points` traces
    a camera's primary rays against `relighter.caster`).

    Raises:
        RelightError: the layer is unreadable, not multiview, stale or corrupt, or `shadows` is not
            'embree' (shadow maps are fitted to one view's receivers).
    """
    layer_path = Path(path)
    description = read_cache_layer(layer_path)
    if description.method != "multiview":
        raise RelightError(f"{layer_path}: a {description.method!r} cache, not 'multiview'")
    if shadows != "embree":
        raise RelightError(f"{layer_path}: multiview caches relight with shadows='embree' only, got {shadows!r}")
    check_inputs(layer_path, description)
    table = load_camera_table(layer_path, description)
    views = CachingViews.build(table, [g.to(device) for g in load_view_gbuffers(layer_path, description, table)])
    # A writable copy: Embree and torch both keep references to it; the .npy is mapped read-only.
    occluders = np.array(load_npy(layer_path, description, "occluders"), dtype=np.float32)
    occluder_objects = np.asarray(load_npy(layer_path, description, "occluderObjects"))
    object_paths = decode_paths(load_npy(layer_path, description, "objectPaths"))
    corner_normals = np.asarray(load_npy(layer_path, description, "cornerNormals"))
    normal_mapped = torch.from_numpy(np.array(load_npy(layer_path, description, "normalMapped"), bool)).to(device)
    caster, visibility = embree_visibility(occluders, occluder_objects, object_paths)
    relighter = MultiviewRelighter(views, visibility, description.supersampling, description.exposure_scale,
                                   settings, object_paths, caster, occluder_objects, corner_normals, normal_mapped)
    relighter.description = description
    relighter.set_lights(shot_lights(description, lights_layer))
    return relighter
