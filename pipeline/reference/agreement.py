"""The reference path tracer against Mitsuba 3: the statistics and the environment-light cases.

Both renderers estimate the same image; they must agree within what their Monte Carlo noise
explains. With d = ours - mitsuba per pixel and channel and v = var_ours + var_mitsuba the
variances of the two means (ours from `ReferenceImage.variance`, Mitsuba's from K independent
seeds), the figures are:

* global: per channel, z = sum(d) / sqrt(sum(v)) within +-Z_LIMIT (an image-wide bias);
* local: 4 x 4-pixel blocks, z_b = sum_b(d) / sqrt(sum_b(v)); sum(z_b^2) below the chi-square
  quantile 1 - CHI2_ALPHA of its degrees of freedom (a bias confined to a region: a shadow, a wall);
* energy of the difference: mean(d^2) / mean(v) below MSE_RATIO_LIMIT (1 when the noise explains
  everything);
* per object: the energy ratio sum(ours) / sum(mitsuba) over the pixels that see only that object,
  within ENERGY_LIMIT of 1, with its standard error.

`CASES` is the one list of environment-light comparisons: `tests/test_reference_mitsuba.py` runs it
and `pipeline.benchmarks.reference_agreement` writes its table (at more samples). Mitsuba is
imported only when a case is rendered.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from scipy import stats

from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.reference.stages import OBJECTS, ShotSpec, write_shot
from pipeline.scene import Scene, find_camera, load_scene
from pipeline.scene.camera import camera_rays
from pipeline.scene.types import Camera
from pipeline.tracing import Tracer
from relight_torch.metrics import psnr, rel_mse

NUM_MITSUBA_SEEDS = 4
BLOCK = 4
Z_LIMIT = 4.0
CHI2_ALPHA = 1e-4
MSE_RATIO_LIMIT = 1.3
ENERGY_LIMIT = 0.01


@dataclasses.dataclass(frozen=True)
class Comparison:
    """Figures of one comparison (see the module doc)."""

    z_global: np.ndarray
    chi2_per_dof: float
    chi2_limit_per_dof: float
    mse_ratio: float
    psnr: float
    rel_mse: float

    def passed(self) -> bool:
        return bool(
            np.abs(self.z_global).max() <= Z_LIMIT
            and self.chi2_per_dof <= self.chi2_limit_per_dof
            and self.mse_ratio <= MSE_RATIO_LIMIT
        )

    def describe(self) -> str:
        return (
            f"z per channel {np.round(self.z_global, 2).tolist()}, block chi2/dof {self.chi2_per_dof:.3f} "
            f"(limit {self.chi2_limit_per_dof:.3f}), mean(d^2)/mean(var) {self.mse_ratio:.3f}, "
            f"PSNR {self.psnr:.1f} dB, relMSE {self.rel_mse:.2e}"
        )


def compare(
    ours: np.ndarray, ours_variance: np.ndarray, theirs: np.ndarray, theirs_variance: np.ndarray, keep: np.ndarray
) -> Comparison:
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
    return Comparison(
        z_global=z_global,
        chi2_per_dof=chi2 / dof,
        chi2_limit_per_dof=float(stats.chi2.ppf(1.0 - CHI2_ALPHA, dof)) / dof,
        mse_ratio=float(np.mean(difference**2) / np.mean(variance)),
        psnr=psnr(ours[keep], theirs[keep]),
        rel_mse=rel_mse(ours[keep], theirs[keep]),
    )


@dataclasses.dataclass(frozen=True)
class Case:
    """One environment-light comparison: a shot (`stages.ShotSpec`), bounces and samples."""

    name: str
    shot: ShotSpec
    max_bounces: int
    spp: int


CASES = (
    Case("constant_direct", ShotSpec("constant"), 0, 192),
    Case("constant_gi", ShotSpec("constant"), 3, 128),
    Case("latlong_direct", ShotSpec("latlong"), 0, 192),
    Case("latlong_gi", ShotSpec("latlong"), 3, 128),
)


@dataclasses.dataclass(frozen=True)
class ObjectEnergy:
    """sum(ours) / sum(mitsuba) over the pixels that see only one object, with its standard error."""

    path: str
    num_pixels: int
    ratio: float
    sigma: float


@dataclasses.dataclass(frozen=True)
class Agreement:
    """A case's comparison, per-object energy ratios and the images behind them."""

    case: Case
    spp: int
    comparison: Comparison
    objects: tuple[ObjectEnergy, ...]
    ours: np.ndarray
    theirs: np.ndarray
    seconds_ours: float

    def energy_passed(self) -> bool:
        return all(abs(o.ratio - 1.0) <= ENERGY_LIMIT for o in self.objects)


def render_mitsuba(scene: Scene, camera: Camera, max_bounces: int, spp: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean, variance of the mean), each (H, W, 3) float64, from NUM_MITSUBA_SEEDS Mitsuba renders."""
    from pipeline.reference import mitsuba_scene  # Mitsuba is a test dependency

    runs = np.stack(
        [
            mitsuba_scene.render(scene, camera, max_bounces, max(1, spp // NUM_MITSUBA_SEEDS), seed=seed)
            for seed in range(NUM_MITSUBA_SEEDS)
        ]
    ).astype(np.float64)
    return runs.mean(axis=0), runs.var(axis=0, ddof=1) / NUM_MITSUBA_SEEDS


def object_masks(scene: Scene, camera: Camera, num_offsets: int = 4) -> np.ndarray:
    """(H, W) int: the object id every one of a num_offsets^2 grid of rays in the pixel hits, -1 where
    they differ or miss (mixed pixels are left out of the per-object sums)."""
    tracer = Tracer(scene.geometry)
    grid = np.linspace(0.0, 1.0, num_offsets, dtype=np.float32)
    ids = None
    for dy in grid:
        for dx in grid:
            offsets = np.broadcast_to(np.array([dx, dy], np.float32), (camera.height, camera.width, 2))
            origins, directions = (a.reshape(-1, 3) for a in camera_rays(camera, np.ascontiguousarray(offsets)))
            hit = tracer.intersect(origins, directions).object_id.reshape(camera.height, camera.width)
            ids = hit if ids is None else np.where(ids == hit, ids, -1)
    return ids


def run_case(case: Case, directory: Path, spp: int | None = None, seed: int = 7) -> Agreement:
    """Write the case's shot under `directory`, render it with both renderers and compare."""
    from pipeline.reference import mitsuba_scene

    spp = spp or case.spp
    scene = load_scene(str(write_shot(Path(directory), case.shot)))
    camera = find_camera(scene, case.shot.camera)
    ours = PathTracer(scene, ReferenceSettings(spp=spp, max_bounces=case.max_bounces, seed=seed)).render(camera)
    theirs, theirs_variance = render_mitsuba(scene, camera, case.max_bounces, spp)
    keep = ~mitsuba_scene.light_footprint_mask(scene, camera)
    comparison = compare(ours.mean, ours.variance, theirs, theirs_variance, keep)
    ids = object_masks(scene, camera)
    paths = [obj.path for obj in scene.objects]
    energies = []
    for path in OBJECTS:
        mask = (ids == paths.index(path)) & keep
        ours_sum, theirs_sum = float(ours.mean[mask].sum()), float(theirs[mask].sum())
        variance = float(ours.variance[mask].sum()) / theirs_sum**2 + float(theirs_variance[mask].sum()) * (
            ours_sum**2 / theirs_sum**4
        )
        energies.append(ObjectEnergy(path, int(mask.sum()), ours_sum / theirs_sum, float(np.sqrt(variance))))
    return Agreement(case, spp, comparison, tuple(energies), ours.mean, theirs, ours.seconds)
