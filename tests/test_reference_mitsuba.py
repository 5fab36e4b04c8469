"""The reference path tracer against an independent renderer, Mitsuba 3 (`tests/mitsuba_convert.py`).

Both renderers estimate the same image; they must agree within what their Monte Carlo noise
explains. With d = ours - mitsuba per pixel and channel and v = var_ours + var_mitsuba the
variances of the two means (ours from `ReferenceImage.variance`, Mitsuba's from K independent
seeds), the checks are:

* global: per channel, z = sum(d) / sqrt(sum(v)) within +-Z_LIMIT (an image-wide bias);
* local: 4 x 4-pixel blocks, z_b = sum_b(d) / sqrt(sum_b(v)); sum(z_b^2) below the chi-square
  quantile 1 - CHI2_ALPHA of its degrees of freedom (a bias confined to a region: a shadow, a wall);
* energy of the difference: mean(d^2) / mean(v) below MSE_RATIO_LIMIT (1 when the noise explains
  everything).

Measured when written (2 cores): Cornell box direct z in [-1, 1], GI z in [-1.3, 0.3], MSE
ratio 0.9-1.1. Pixels whose footprint shows a light are left out (our lights are invisible to
camera rays, Mitsuba's emitter shapes are black), and the Cornell ceiling is opened above the
lamp, as in the published box: our lights are not occluders, so with the whole ceiling the patch
behind the lamp shows through it and adds 0.75 % to the GI image (measured: z = 2.2 at 32 x 32,
256 spp; with the opening z = 0). On failure, ours, Mitsuba's and the difference are written as
EXRs under the test's tmp_path.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy import stats

from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.scene import Scene, find_camera, load_scene
from pipeline.scene.types import Camera, MaterialInput
from pipeline.scenes import SCENES
from pipeline.scenes import leaves as leaves_scene
from relight_torch.io.exr import write_exr
from relight_torch.lights.light import LightKind
from relight_torch.metrics import psnr, rel_mse

pytest.importorskip("mitsuba")
import mitsuba_convert  # noqa: E402  (needs mitsuba)

pytestmark = pytest.mark.slow

NUM_MITSUBA_SEEDS = 4
BLOCK = 4
Z_LIMIT = 4.0
CHI2_ALPHA = 1e-4
MSE_RATIO_LIMIT = 1.3


@dataclasses.dataclass(frozen=True)
class Comparison:
    """Figures of one comparison (see the module doc)."""

    z_global: np.ndarray
    chi2_per_dof: float
    chi2_limit_per_dof: float
    mse_ratio: float
    psnr: float
    rel_mse: float

    def describe(self) -> str:
        return (f"z per channel {np.round(self.z_global, 2).tolist()}, block chi2/dof {self.chi2_per_dof:.3f} "
                f"(limit {self.chi2_limit_per_dof:.3f}), mean(d^2)/mean(var) {self.mse_ratio:.3f}, "
                f"PSNR {self.psnr:.1f} dB, relMSE {self.rel_mse:.2e}")


def _compare(ours: np.ndarray, ours_variance: np.ndarray, theirs: np.ndarray, theirs_variance: np.ndarray,
             keep: np.ndarray) -> Comparison:
    """Statistics of ours - theirs over the kept (H, W) pixels (H, W multiples of BLOCK)."""
    height, width, _ = ours.shape
    keep3 = np.broadcast_to(keep[..., None], ours.shape)
    difference = np.where(keep3, ours.astype(np.float64) - theirs, 0.0)
    variance = np.where(keep3, ours_variance.astype(np.float64) + theirs_variance, 0.0)
    z_global = difference.sum((0, 1)) / np.sqrt(variance.sum((0, 1)))

    def blocks(image: np.ndarray) -> np.ndarray:
        return image.reshape(height // BLOCK, BLOCK, width // BLOCK, BLOCK, 3).sum((1, 3))

    block_difference, block_variance = blocks(difference), blocks(variance)
    # A block both renderers see as exactly black (no light reaches it) carries no statistic.
    lit = block_variance > 0
    if np.any(block_difference[~lit] != 0):
        raise AssertionError("a block is noiseless in both renders yet they differ")
    chi2 = float(np.sum(block_difference[lit] ** 2 / block_variance[lit]))
    dof = int(lit.sum())
    return Comparison(z_global=z_global, chi2_per_dof=chi2 / dof,
                      chi2_limit_per_dof=float(stats.chi2.ppf(1.0 - CHI2_ALPHA, dof)) / dof,
                      mse_ratio=float(np.mean(difference**2) / np.mean(variance)),
                      psnr=psnr(ours[keep], theirs[keep]), rel_mse=rel_mse(ours[keep], theirs[keep]))


def _open_ceiling_above_lamp(scene: Scene) -> Scene:
    """The Cornell box with the ceiling cut open over the lamp's rectangle (the published box's
    opening): replaces the ceiling's triangles (all corners above the lamp) by four that frame it."""
    lamp = next(light for light in scene.lights if light.kind is LightKind.RECT)
    half = np.abs(lamp.world_from_light[:3, :2] @ np.diag([lamp.width / 2, lamp.height / 2])).sum(axis=1)
    centre = lamp.world_from_light[:3, 3]
    hole_low, hole_high = centre - half, centre + half
    geometry = scene.geometry
    ceiling = np.all(geometry.positions[:, :, 1] > centre[1], axis=1)
    corners = geometry.positions[ceiling].reshape(-1, 3)
    (x0, y, z0), (x1, _, z1) = corners.min(axis=0), corners.max(axis=0)
    hx0, hz0, hx1, hz1 = hole_low[0], hole_low[2], hole_high[0], hole_high[2]
    frame = [(x0, z0, x1, hz0), (x0, hz1, x1, z1), (x0, hz0, hx0, hz1), (hx1, hz0, x1, hz1)]
    # (x, z) corners in this order wind each triangle to face down (-Y), into the box.
    quads = np.array([[(a, y, b), (c, y, b), (c, y, d), (a, y, b), (c, y, d), (a, y, d)] for a, b, c, d in frame],
                     np.float32).reshape(-1, 3, 3)
    num_new = quads.shape[0]
    first = np.flatnonzero(ceiling)[0]

    def replaced(array: np.ndarray, new: np.ndarray) -> np.ndarray:
        return np.concatenate([array[~ceiling], new.astype(array.dtype)])

    geometry = dataclasses.replace(
        geometry,
        positions=replaced(geometry.positions, quads),
        normals=replaced(geometry.normals, np.broadcast_to([0.0, -1.0, 0.0], quads.shape)),
        uvs=replaced(geometry.uvs, np.zeros((num_new, 3, 2))),
        material_ids=replaced(geometry.material_ids, np.full(num_new, geometry.material_ids[first])),
        object_ids=replaced(geometry.object_ids, np.full(num_new, geometry.object_ids[first])))
    return dataclasses.replace(scene, geometry=geometry)


def _without_textures_and_shaped_lights(scene: Scene) -> Scene:
    """The glossy scene reduced to what converts exactly: textured inputs become their constant
    fallbacks (the brick floor turns a plain rough dielectric, its normal map flat) and lights
    with ShapingAPI (the spot) are dropped, as Mitsuba has no shaped sphere light."""
    materials = []
    for material in scene.materials:
        changes = {name: MaterialInput(np.asarray(value.value)) for name, value in vars(material).items()
                   if isinstance(value, MaterialInput) and value.texture is not None}
        if "normal" in changes:
            changes["normal"] = MaterialInput(np.array([0.0, 0.0, 1.0], np.float32))
        materials.append(material.replace(**changes))
    lights = [light for light in scene.lights if light.shaping is None]
    return dataclasses.replace(scene, materials=materials, lights=lights)


def _render_both(scene: Scene, camera: Camera, max_bounces: int, spp: int):
    ours = PathTracer(scene, ReferenceSettings(spp=spp, max_bounces=max_bounces, seed=7)).render(camera)
    runs = np.stack([mitsuba_convert.render(scene, camera, max_bounces, spp // NUM_MITSUBA_SEEDS, seed=seed)
                     for seed in range(NUM_MITSUBA_SEEDS)]).astype(np.float64)
    theirs = runs.mean(axis=0)
    theirs_variance = runs.var(axis=0, ddof=1) / NUM_MITSUBA_SEEDS
    return ours, theirs, theirs_variance


def _check(scene: Scene, camera: Camera, max_bounces: int, spp: int, tmp_path) -> Comparison:
    ours, theirs, theirs_variance = _render_both(scene, camera, max_bounces, spp)
    keep = ~mitsuba_convert.light_footprint_mask(scene, camera)
    comparison = _compare(ours.mean, ours.variance, theirs, theirs_variance, keep)
    failed = (np.abs(comparison.z_global).max() > Z_LIMIT
              or comparison.chi2_per_dof > comparison.chi2_limit_per_dof
              or comparison.mse_ratio > MSE_RATIO_LIMIT)
    if failed:
        for name, image in (("ours", ours.mean), ("mitsuba", theirs), ("difference", ours.mean - theirs)):
            write_exr(tmp_path / f"{name}.exr", {c: image[..., i].astype(np.float32) for i, c in enumerate("RGB")})
        raise AssertionError(f"reference and Mitsuba disagree beyond their noise ({tmp_path}): "
                             f"{comparison.describe()}")
    return comparison


@pytest.fixture(scope="module")
def cornell_box(tmp_path_factory) -> Scene:
    directory = tmp_path_factory.mktemp("cornell_box")
    bundled = SCENES["cornell_box"]
    scene = load_scene(str(bundled.write(directory)), width=32, height=32)
    return _open_ceiling_above_lamp(scene)


@pytest.mark.parametrize("max_bounces, spp", [(0, 128), (4, 192)], ids=["direct", "gi"])
def test_cornell_box_matches_mitsuba(cornell_box, max_bounces, spp, tmp_path):
    _check(cornell_box, find_camera(cornell_box, SCENES["cornell_box"].camera), max_bounces, spp, tmp_path)


def test_glossy_scene_matches_mitsuba(tmp_path):
    bundled = SCENES["glossy"]
    scene = load_scene(str(bundled.write(tmp_path / "scene")), width=40, height=32)
    scene = _without_textures_and_shaped_lights(scene)
    _check(scene, find_camera(scene, bundled.camera), 2, 96, tmp_path)


def test_comparison_detects_a_two_percent_bias():
    """The statistics have power: a 2 % brighter copy of an image with
    a noise level like the Cornell GI test (relative sigma 5 % per pixel, 32 x 32) fails the global
    z-test (expected z = 8)."""
    rng = np.random.default_rng(0)
    truth = rng.uniform(0.05, 0.5, (32, 32, 3))
    variance = (0.05 * truth) ** 2
    ours = truth * 1.02 + rng.normal(0.0, np.sqrt(variance))
    theirs = truth + rng.normal(0.0, np.sqrt(variance))
    comparison = _compare(ours, variance, theirs, variance, np.ones((32, 32), bool))
    assert np.all(comparison.z_global > Z_LIMIT), comparison.describe()
    unbiased = _compare(truth + rng.normal(0.0, np.sqrt(variance)), variance, theirs, variance,
                        np.ones((32, 32), bool))
    assert np.all(np.abs(unbiased.z_global) < Z_LIMIT) and unbiased.mse_ratio < MSE_RATIO_LIMIT
    assert math.isfinite(unbiased.psnr)


def _leaves_for_mitsuba(scene: Scene) -> Scene:
    """The leaves scene reduced to what converts exactly: the leaves' and lattice's colour textures
    become their constant fallback (their binary alpha cut-outs stay), and the 1-degree sun a
    zero-angle one of the same irradiance (Mitsuba's 'directional')."""
    materials = [material.replace(diffuse_color=MaterialInput(np.asarray(material.diffuse_color.value)))
                 for material in scene.materials]
    lights = [dataclasses.replace(light, angle=0.0, intensity=leaves_scene.SUN_IRRADIANCE)
              if light.kind is LightKind.DISTANT else light for light in scene.lights]
    return dataclasses.replace(scene, materials=materials, lights=lights)


def test_leaves_cut_outs_match_mitsuba(tmp_path):
    """Cut-out leaves and lattice (textured opacity + opacityThreshold) in camera and shadow rays
    against Mitsuba's 'mask' BSDF under 'volpath'."""
    bundled = SCENES["leaves"]
    scene = _leaves_for_mitsuba(load_scene(str(bundled.write(tmp_path / "scene")), width=32, height=24))
    _check(scene, find_camera(scene, bundled.camera), 0, 128, tmp_path)
