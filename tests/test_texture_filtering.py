"""Pixel-footprint filtering of textures and normal maps in the deep framebuffer.

The reference path tracer point-samples the textures at each path's hit, so a pixel of the
reference is the average of its surface's shading over the pixel; the bake must converge to it.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.bake.deep_framebuffer import bake_deep_framebuffer, texel_density
from pipeline.bake.direct.bake import bake_direct
from pipeline.benchmarks.texture_filtering import CLASSES, pixel_classes
from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES
from relight_torch.direct.relighter import open_relighter
from relight_torch.io.exr import write_rgb_exr


@pytest.mark.slow
def test_normal_mapped_floor_converges_to_the_pixel_average(tmp_path):
    """Glossy at 96 x 72, 8 x 8 material samples per sub-sample: the brick floor (textured pixels,
    a few hundred texels each) reaches 37 dB against the reference. Averaging the normals and
    widening the lobe from their spread held it to 33.6 dB with the same samples: bevel normals
    that face away from the camera are black in the reference."""
    width, height, spp, threshold = 96, 72, 256, 37.0
    shot = SCENES["glossy"].write(tmp_path)
    scene = load_scene(shot, width=width, height=height)
    camera = find_camera(scene, SCENES["glossy"].camera)
    cache = bake_direct(scene, camera, tmp_path / "cache", "glossy", supersampling=2, texture_samples=8)
    image = open_relighter(cache).render().cpu().numpy()
    reference = PathTracer(scene, ReferenceSettings(spp=spp, max_bounces=0, seed=7)).render(camera)
    textured = pixel_classes(scene, camera) == CLASSES.index("textured")
    error = np.mean(np.square(np.clip(image, 0, 1) - np.clip(reference.mean, 0, 1))[textured])
    floor_psnr = 10.0 * np.log10(1.0 / error)
    if floor_psnr < threshold:
        for name, values in (
            ("relit", image),
            ("reference", reference.mean),
            ("error", np.abs(image - reference.mean)),
        ):
            write_rgb_exr(tmp_path / f"{name}.exr", values)
    assert floor_psnr >= threshold, f"textured pixels at {floor_psnr:.2f} dB; images under {tmp_path}"


def test_constant_materials_are_not_refined(tmp_path):
    """More texture samples change nothing where no material or normal varies inside a sub-sample
    (the Cornell box has no textures): only sub-samples astride a block's crease, whose normals
    differ, are refined. The cost follows what each pixel needs."""
    shot = SCENES["cornell_box"].write(tmp_path)
    scene = load_scene(shot, width=24, height=24)
    camera = find_camera(scene, SCENES["cornell_box"].camera)
    probe = bake_deep_framebuffer(scene, camera, 2, 2).gbuffer
    refined = bake_deep_framebuffer(scene, camera, 2, 8).gbuffer
    changed = np.zeros(probe.pixel_index.shape[0], bool)
    for field in dataclasses.fields(probe.params):
        before, after = getattr(probe.params, field.name).numpy(), getattr(refined.params, field.name).numpy()
        changed |= np.any((before != after).reshape(before.shape[0], -1), axis=-1)
    changed |= np.any(refined.normal.numpy() != probe.normal.numpy(), axis=-1)
    crease = np.abs(np.sum(probe.normal.numpy() * probe.geometric_normal.numpy(), axis=-1)) < 1.0 - 1e-5
    assert changed.any() and not changed[~crease].any()
    assert changed.mean() < 0.05


def test_refined_textured_samples_differ_from_the_probe(tmp_path):
    """On the glossy scene's brick floor the second pass does run: the filtered albedo changes."""
    shot = SCENES["glossy"].write(tmp_path)
    scene = load_scene(shot, width=32, height=24)
    camera = find_camera(scene, SCENES["glossy"].camera)
    probe = bake_deep_framebuffer(scene, camera, 1, 2).gbuffer
    refined = bake_deep_framebuffer(scene, camera, 1, 4).gbuffer
    floor = [i for i, m in enumerate(scene.materials) if m.path.endswith("Bricks")]
    on_floor = np.isin(probe.material_id.numpy(), floor)
    changed = np.any(refined.params.diffuse_color.numpy() != probe.params.diffuse_color.numpy(), axis=-1)
    assert changed[on_floor].mean() > 0.5
    assert not changed[~on_floor].any() or changed[~on_floor].mean() < changed[on_floor].mean()


def test_texel_density(tmp_path):
    """Texels per unit of texture coordinate: the glossy bricks are 512-texel images, st = uv."""
    shot = SCENES["glossy"].write(tmp_path)
    scene = load_scene(shot, width=8, height=8)
    density = texel_density(scene)
    for material, value in zip(scene.materials, density, strict=True):
        assert value == (512.0 if material.path.endswith("Bricks") else 0.0), material.path
