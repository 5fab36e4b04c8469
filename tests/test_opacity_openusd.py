"""Opacity on OpenUSD's own UsdPreviewSurface test stages (tests/data/materials/PROVENANCE.md):
cut-outs by opacityThreshold, textured opacity, and translucent (partially opaque) spheres, traced
with the tracer every renderer shares, and rendered by the reference without an opacity warning.

testPreviewSurfacePrimvarReaderOpacity reads a per-face `displayOpacity` primvar: the soup carries
no per-face primvars but 'st' and displayColor, so it still warns (out of scope here) and renders
opaque.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.scene import load_scene
from pipeline.scene.types import Camera
from pipeline.tracing import Tracer
from relight_torch.io.images import read_image
from relight_torch.lights.light import Light, LightKind

DATA = Path(__file__).parent / "data" / "materials"
STAGES = ("OpacityThreshold", "TextureOpacity", "Translucent", "PrimvarReaderOpacity")


def _stage(name):
    return load_scene(str(DATA / f"testPreviewSurface{name}.usda"))


def _camera(scene) -> Camera:
    """A camera 8 units in front of the scene's bounds (+Z), looking down -Z, 16 x 16."""
    low, high = scene.bounds
    world_from_camera = np.eye(4)
    world_from_camera[:3, 3] = [(low[0] + high[0]) / 2, (low[1] + high[1]) / 2, high[2] + 8.0]
    size = float(np.max(high - low))
    return Camera(
        "/Test/Camera", world_from_camera, 50.0, 50.0 * size / 8.0, 50.0 * size / 8.0, 0.0, 0.0, (0.1, 1000.0), 16, 16
    )


@pytest.mark.parametrize("name", STAGES)
def test_reference_renders_without_an_opacity_warning(name):
    scene = _stage(name)
    sun = Light("/Test/Sun", LightKind.DISTANT, angle=0.0, intensity=3.0)
    scene = dataclasses.replace(scene, lights=[sun], warnings=list(scene.warnings))
    image = PathTracer(scene, ReferenceSettings(spp=2, max_bounces=0)).render(_camera(scene)).mean
    assert np.isfinite(image).all()
    opacity_warnings = [w for w in scene.warnings if "opacity" in w.replace(scene.source, "").lower()]
    if name == "PrimvarReaderOpacity":
        assert len(opacity_warnings) == 1 and "displayOpacity" in opacity_warnings[0]
    else:
        assert opacity_warnings == []


def test_opacity_thresholds_cut_the_texture_as_storm():
    """Six 1 x 1 planes at x = 1.5 k read textureCutout.png's alpha with thresholds 0, 0.1, 0.3,
    0.5, 0.9, 1. Rays at texel centres (where bilinear filtering returns the texel) stop exactly
    where the texel's alpha reaches the threshold; threshold 0 leaves partial opacity, met with
    probability alpha."""
    scene = _stage("OpacityThreshold")
    tracer = Tracer.for_scene(scene)
    alpha = read_image(str(DATA / "textureCutout.png"), "auto").pixels[..., 3]
    size = alpha.shape[0]
    centres = (np.arange(size) + 0.5) / size
    s, t = np.meshgrid(centres, centres[::-1])  # row 0 of the image is the top: t = 1
    for k, threshold in enumerate((0.0, 0.1, 0.3, 0.5, 0.9, 1.0)):
        origins = np.stack([1.5 * k + s.ravel(), t.ravel(), np.ones(s.size)], -1).astype(np.float32)
        directions = np.broadcast_to(np.float32([0, 0, -1]), origins.shape).copy()
        stopped = tracer.occluded(origins, directions, np.full(s.size, 2.0, np.float32))
        if threshold > 0:
            # A texel whose alpha equals the threshold, beside one below it, is a knife edge: the
            # hit's float32 barycentrics (rounded as Embree's code path for the CPU does) put the
            # sample a hair off the texel centre, where the bilinear blend falls an ulp below the
            # texel (265 of 65,536 rays at threshold 1 on one machine). Every other texel must
            # stop exactly.
            below = np.pad(alpha < threshold, 1, constant_values=False)
            neighbour_below = np.any(
                [below[1 + dy : 1 + dy + size, 1 + dx : 1 + dx + size] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], 0
            )
            decided = ~((np.abs(alpha - threshold) < 1e-6) & neighbour_below).ravel()
            np.testing.assert_array_equal(
                stopped[decided], (alpha.ravel() >= threshold)[decided], err_msg=f"threshold {threshold}"
            )
        else:
            expected = float(alpha.mean())
            sigma = np.sqrt(np.sum(alpha * (1 - alpha))) / alpha.size
            assert abs(stopped.mean() - expected) < 5 * sigma


def test_texture_opacity_of_an_rgb_image_is_opaque():
    """The plane's opacity reads output 'a' of checkerboard.png, an RGB image: UsdUVTexture's alpha
    is then 1, so nothing is cut out (the checker's colours do not leak into opacity)."""
    scene = _stage("TextureOpacity")
    assert Tracer.for_scene(scene).opacity is None


def test_translucent_spheres_let_light_through_by_their_opacity():
    """Rays meeting each triangle of the 0.8 and 0.6 opacity spheres once, from just outside, are
    stopped in proportion to the opacity (stochastic presence)."""
    scene = _stage("Translucent")
    tracer = Tracer.for_scene(scene)
    geometry = scene.geometry
    for material_id, material in enumerate(scene.materials):
        opacity = float(material.opacity.value[0])
        rows = np.flatnonzero(geometry.material_ids == material_id)
        if opacity >= 1.0 or rows.size == 0:
            continue
        corners = geometry.positions[rows].astype(np.float64)
        centroid = corners.mean(axis=1)
        normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        area = np.linalg.norm(normal, axis=-1)
        keep = area > 1e-12
        normal = normal[keep] / area[keep, None]
        gap = 10.0 * tracer.epsilon
        origins = (centroid[keep] + gap * normal).astype(np.float32)
        stopped = tracer.occluded(origins, (-normal).astype(np.float32), np.full(keep.sum(), 2 * gap, np.float32))
        sigma = np.sqrt(opacity * (1 - opacity) / stopped.size)
        assert abs(stopped.mean() - opacity) < 5 * sigma, (material.path, stopped.mean(), opacity)
