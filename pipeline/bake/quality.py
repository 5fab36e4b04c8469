"""Quality-driven sizing: `relight bake ... --quality PSNR` picks the method's sizes from pilot bakes.

1. Pilot: the shot at a reduced size (long side `pilot_side`, aspect kept) and its path-tracer
   reference at the method's bounce count, with enough spp that the reference's own noise is
   NOISE_HEADROOM_DB below the target (`reference_for`).
2. The method's ladder steps (`BakeMethod.ladder`, `pipeline.bake.methods`), cheapest first, are
   baked at the pilot size through its adapter (`BakeMethod.adapter`) and relit under the shot's
   lights; a step may give several variants from one bake (transfer's kept coefficients). The first step with a variant
   whose pilot PSNR reaches target + margin stops the search, and its smallest such variant (cache
   bytes) is chosen. Steps grow every size that costs cache bytes, so a later step cannot be
   smaller at equal accuracy; transfer's 4x more gathers per step is the exception taken as a
   heuristic: it stops at the first gather count that reaches the target.
3. The chosen sizes are baked at the full size and measured against a full-size reference (same
   noise rule). If that misses the target, the ladder's later steps are measured at the full size
   in turn (`climb_at_full_size`) until one reaches it: what the pilot's coarse pixels cannot show
   (the near-field indirect light where objects meet the floor, texture aliasing) is what misses.
   A frame of more than MEASURE_PIXELS pixels is measured on its centre window at the full pixel
   density (`measurement_window`), then baked whole.
4. The cache layer's parameters record the choice (the method's own parameters hold the bake
   sizes; qualityChoice all of them, relight-time ones such as the illumination cut size included)
   and: qualityTarget, qualityPredicted (pilot PSNR; nan for a step only measured at full size),
   qualityMeasured (full size), qualityRawPsnr,
   qualityEnergyRatio (mean(image) / mean(reference) at full size), qualityTargetMet (1 when the
   full-size PSNR reaches the target, else 0), qualityReferenceSpp, qualityPilot ('WxH') and
   qualityMeasuredSize ('WxH': the frame, or the window measured).

PSNRs here are noise-corrected: the reference's variance (`ReferenceImage.variance`, over pixels
it does not saturate) is subtracted from the squared error, which it adds on average; the raw
PSNR (`qualityRawPsnr`) is kept beside it.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.bake.adapter import MethodAdapter, format_params
from pipeline.bake.methods import bake_method
from pipeline.errors import RelightError
from pipeline.reference.path_tracer import PathTracer, ReferenceImage, ReferenceSettings
from pipeline.scene.camera import crop
from pipeline.scene.types import Camera, Scene
from relight_torch.cache.layer import content_hash, read_cache_layer, write_cache_layer
from relight_torch.metrics import psnr_from_mse

log = logging.getLogger(__name__)

NOISE_HEADROOM_DB = 10.0
"""How far below the target the reference's own noise must be (its MSE then adds ~0.4 dB)."""
MAX_REFERENCE_SPP = 4096
START_SPP = 32
MEASURE_PIXELS = 640 * 480
"""Full-size checks of larger images measure a window of at most this many pixels at the centre of
the frame (`measurement_window`): a reference of a film-size frame at the checks' noise floor takes
hours, while a window at the full pixel density shows the same aliasing and the same error per
pixel of the subject at the frame's centre."""


@dataclass(frozen=True)
class Measured:
    """One variant measured against a reference (on the pilot or at full size): its single-variant
    point, PSNR (noise-corrected and raw), energy ratio mean(image) / mean(reference), cache bytes,
    the layer baked (a pilot's is removed with the pilot folder) and the index of its ladder step."""

    point: dict[str, object]
    psnr_db: float
    raw_db: float
    energy_ratio: float
    cache_bytes: float
    layer: Path
    step: int


@dataclass(frozen=True)
class QualityResult:
    """What `bake_for_quality` chose and measured.

    Attributes:
        layer: the cache layer written.
        point: the chosen sizes (the adapter's bake point).
        predicted_db: the pilot's PSNR of that point.
        measured_db: the full-size PSNR (noise-corrected); raw_db: without the correction.
        target_met: measured_db reaches the target.
        energy_ratio: mean(image) / mean(reference) at full size.
        reference_spp: spp of the full-size reference.
        pilot: (width, height) of the pilot.
        candidates: every pilot measurement, in the order made.
        measured_size: (width, height) the full-size check measured: the frame, or its centre
            window at the same pixel density (`measurement_window`).
    """

    layer: Path
    point: dict[str, object]
    predicted_db: float
    measured_db: float
    raw_db: float
    target_met: bool
    energy_ratio: float
    reference_spp: int
    pilot: tuple[int, int]
    candidates: tuple[Measured, ...]
    measured_size: tuple[int, int]


def pilot_size(width: int, height: int, pilot_side: int) -> tuple[int, int]:
    """(width, height) scaled so the long side is at most `pilot_side`, aspect kept, each >= 1."""
    scale = min(1.0, pilot_side / max(width, height))
    return max(1, round(width * scale)), max(1, round(height * scale))


def resized(scene: Scene, camera: Camera, width: int, height: int) -> tuple[Scene, Camera]:
    """The scene and camera at another image size (cameras are looked up by path)."""
    resized = dataclasses.replace(camera, width=width, height=height)
    return dataclasses.replace(scene, cameras={**scene.cameras, camera.path: resized}), resized


def measurement_window(scene: Scene, camera: Camera, max_pixels: int | None = None) -> tuple[Scene, Camera]:
    """The scene and camera a full-size check measures: the shot itself up to `max_pixels`
    (default `MEASURE_PIXELS`), else the centre window of the frame with its aspect, at the same
    pixel density (`camera.crop`), its sides multiples of 8 (every indirect scale and level
    stride divides them)."""
    max_pixels = MEASURE_PIXELS if max_pixels is None else max_pixels
    if camera.width * camera.height <= max_pixels:
        return scene, camera
    scale = math.sqrt(max_pixels / (camera.width * camera.height))
    width, height = (max(8, int(side * scale) // 8 * 8) for side in (camera.width, camera.height))
    window = crop(camera, (camera.width - width) // 2, (camera.height - height) // 2, width, height)
    return dataclasses.replace(scene, cameras={**scene.cameras, camera.path: window}), window


def noise_mse(reference: ReferenceImage) -> float:
    """The MSE the reference's own noise adds to a clamped comparison (pixels it does not saturate)."""
    unsaturated = reference.mean < 1.0
    return float(np.mean(np.where(unsaturated, reference.variance, 0.0)))


def corrected_psnr(image: np.ndarray, reference: ReferenceImage) -> tuple[float, float]:
    """(noise-corrected PSNR, raw PSNR) of `image` against `reference` (see the module doc).

    The corrected MSE is floored at a tenth of the noise MSE: below that the reference cannot tell.
    """
    raw = float(np.mean((np.clip(image, 0.0, 1.0) - np.clip(reference.mean, 0.0, 1.0)) ** 2))
    noise = noise_mse(reference)
    return psnr_from_mse(max(raw - noise, 0.1 * noise, 1e-12)), psnr_from_mse(raw)


def reference_for(
    scene: Scene, camera: Camera, bounces: int, target_db: float, headroom_db: float = NOISE_HEADROOM_DB
) -> ReferenceImage:
    """The path tracer's image at START_SPP, re-rendered once with more spp if its noise floor is
    less than `headroom_db` above `target_db` (at most MAX_REFERENCE_SPP)."""
    spp = START_SPP
    while True:
        reference = PathTracer(scene, ReferenceSettings(spp=spp, max_bounces=bounces)).render(camera)
        floor_db = psnr_from_mse(noise_mse(reference))
        wanted = target_db + headroom_db
        if floor_db >= wanted or spp >= MAX_REFERENCE_SPP:
            return reference
        spp = min(MAX_REFERENCE_SPP, math.ceil(spp * 10 ** ((wanted - floor_db) / 10) * 1.1))


def _measure(
    adapter: MethodAdapter,
    scene: Scene,
    camera: Camera,
    directory: Path,
    stem: str,
    point: dict[str, object],
    step: int,
    reference: ReferenceImage,
    supersampling: int,
    texture_samples: int,
    time_code: float | None,
) -> list[Measured]:
    """Bake `point` (ladder step `step`) into `directory` and measure each of its variants against `reference`."""
    directory.mkdir(parents=True, exist_ok=True)
    layer = adapter.bake(scene, camera, directory, stem, point, supersampling, texture_samples, time_code)
    out = []
    for variant in adapter.variants(layer, point, "cpu"):
        image = variant.relighter.render().cpu().numpy()
        corrected, raw = corrected_psnr(image, reference)
        energy = float(image.mean() / max(float(reference.mean.mean()), 1e-12))
        out.append(
            Measured(
                _variant_point(point, variant.parameters), corrected, raw, energy, variant.cache_bytes, layer, step
            )
        )
    return out


def climb_at_full_size(
    first: Measured,
    steps: Sequence[dict[str, object]],
    measure: Callable[[int, dict[str, object]], list[Measured]],
    target_db: float,
) -> Measured:
    """After `first` (the pilot's choice measured at full size) missed `target_db`: the ladder's
    `steps` from the pilot's choice's on, measured at full size in turn (`measure(index into
    steps, step)` gives its variants; `first` among the first step's is skipped), the cheapest
    variant (cache bytes) of the first step with one reaching the target, else the best measured."""
    best = first
    for index, step in enumerate(steps):
        measured = [m for m in measure(index, step) if m.point != first.point]
        for variant in measured:
            log.info(
                "quality at full size: %s %.2f dB, %d bytes",
                format_params(variant.point),
                variant.psnr_db,
                variant.cache_bytes,
            )
        passing = [m for m in measured if m.psnr_db >= target_db]
        if passing:
            return min(passing, key=lambda m: m.cache_bytes)
        best = max([best, *measured], key=lambda m: m.psnr_db)
    return best


def _variant_point(ladder_point: dict[str, object], parameters: dict[str, object]) -> dict[str, object]:
    """The single-variant bake point of one measured variant (tuple axes resolved from its parameters)."""
    return {key: (int(parameters[key]) if isinstance(value, tuple) else value) for key, value in ladder_point.items()}


def bake_for_quality(
    scene: Scene,
    camera: Camera,
    out_dir: str | Path,
    stem: str,
    method: str,
    target_db: float,
    supersampling: int = 2,
    texture_samples: int = 2,
    time_code: float | None = None,
    fixed: dict[str, object] | None = None,
    pilot_side: int = 64,
    margin_db: float = 0.5,
    reference_bounces: int | None = None,
    ladder: list[dict[str, object]] | None = None,
    measure_headroom_db: float = NOISE_HEADROOM_DB,
    best_effort: bool = False,
    full_reference: ReferenceImage | None = None,
) -> QualityResult:
    """Bake `method` sized to reach `target_db` PSNR on the shot (see the module doc).

    Args:
        scene, camera: the shot at its full size.
        supersampling: the direct part's (transfer, gather); direct sizes its own.
        fixed: bake-point entries kept as given on every step (e.g. transfer's {'bounces': 2}).
        pilot_side: the pilot's long side in pixels.
        margin_db: added to the target for the pilot (its size differs from the full one).
        reference_bounces: the references' indirect bounces (default: the method's own, its slice of
            the light transport; the shot cache measures against the full frame).
        ladder: the bake points to try, cheapest first (default: the method's registered ladder).
        measure_headroom_db: the full-size reference's noise floor above the target (its noise is
            subtracted from the measured error, so a lower floor costs precision, not bias).
        best_effort: when no step reaches the target on the pilot, bake the best one measured
            (with a warning and qualityTargetMet = 0) instead of failing.
        full_reference: the full-size reference when the caller rendered it already (of
            `measurement_window(scene, camera)`, at the references' bounces and noise floor).

    Raises:
        RelightError: the method has no ladder, or (without `best_effort`) no step reaches the target.
    """
    entry = bake_method(method)
    if ladder is None and not entry.ladder:
        raise RelightError(f"bake --quality: method {method!r} declares no sizing ladder")
    adapter = entry.adapter
    out_dir = Path(out_dir)
    pilot_dir = out_dir / f".{stem}.quality-pilot"
    width, height = pilot_size(camera.width, camera.height, pilot_side)
    pilot_scene, pilot_camera = resized(scene, camera, width, height)
    ladder = [{**step, **(fixed or {})} for step in (entry.ladder if ladder is None else ladder)]
    bounces = adapter.bounces(ladder[0]) if reference_bounces is None else reference_bounces
    pilot_reference = reference_for(pilot_scene, pilot_camera, bounces, target_db + margin_db)
    candidates: list[Measured] = []
    passing: list[Measured] = []
    try:
        for index, step in enumerate(ladder):
            new = _measure(
                adapter,
                pilot_scene,
                pilot_camera,
                pilot_dir / f"step-{index}",
                stem,
                step,
                index,
                pilot_reference,
                supersampling,
                texture_samples,
                time_code,
            )
            for candidate in new:
                log.info(
                    "quality pilot %s: %.2f dB, %d bytes",
                    format_params(candidate.point),
                    candidate.psnr_db,
                    candidate.cache_bytes,
                )
            candidates.extend(new)
            passing = [c for c in new if c.psnr_db >= target_db + margin_db]
            if passing:
                chosen = min(passing, key=lambda c: c.cache_bytes)
                break
        else:
            chosen = max(candidates, key=lambda c: c.psnr_db)
            if not best_effort:
                raise RelightError(
                    f"{scene.source}: bake --quality {target_db:g}: no {method} size reaches it on the pilot "
                    f"(best {chosen.psnr_db:.1f} dB with {chosen.point})"
                )
        ladder_spent = not passing
        window_scene, window = measurement_window(scene, camera)
        windowed = window is not camera

        reference = (
            reference_for(window_scene, window, bounces, target_db, measure_headroom_db)
            if full_reference is None
            else full_reference
        )

        def measure_full_size(directory: Path, point: dict[str, object], step: int) -> list[Measured]:
            """`point` (ladder step `step`) baked at full size (the frame or its window) into `directory`, measured."""
            return _measure(
                adapter,
                window_scene,
                window,
                directory,
                stem,
                point,
                step,
                reference,
                supersampling,
                texture_samples,
                time_code,
            )

        # A whole frame is measured where it is kept: the pilot's choice usually holds.
        (final,) = measure_full_size(pilot_dir / "full-size" if windowed else out_dir, chosen.point, chosen.step)
        log.info(
            "quality: %s measured %.2f dB at full size on %dx%d pixels (pilot %.2f dB)",
            format_params(chosen.point),
            final.psnr_db,
            window.width,
            window.height,
            chosen.psnr_db,
        )
        first = final
        if final.psnr_db < target_db and not ladder_spent:
            final = climb_at_full_size(
                first,
                ladder[chosen.step :],
                lambda index, step: measure_full_size(
                    pilot_dir / f"full-size-{chosen.step + index}", step, chosen.step + index
                ),
                target_db,
            )
        layer = final.layer
        if windowed or final is not first:  # measured on the window, or a variant of a larger bake
            layer = adapter.bake(scene, camera, out_dir, stem, final.point, supersampling, texture_samples, time_code)
    finally:
        shutil.rmtree(pilot_dir, ignore_errors=True)
    point, measured_db = final.point, final.psnr_db
    if ladder_spent:
        log.warning(
            "%s: quality target %g dB not reached: measured %.2f dB with the best %s size of the ladder (%s)",
            scene.source,
            target_db,
            measured_db,
            method,
            format_params(point),
        )
    elif measured_db < target_db:
        log.warning(
            "%s: quality target %g dB not reached at full size: measured %.2f dB with %s, the best of the ladder's "
            "remaining sizes",
            scene.source,
            target_db,
            measured_db,
            format_params(point),
        )
    predicted = next((c.psnr_db for c in candidates if c.point == point), math.nan)
    reference_spp = round(reference.num_paths / (window.width * window.height))
    result = QualityResult(
        layer,
        point,
        predicted,
        measured_db,
        final.raw_db,
        measured_db >= target_db,
        final.energy_ratio,
        reference_spp,
        (width, height),
        tuple(candidates),
        (window.width, window.height),
    )
    _record(result, target_db)
    return result


def _record(result: QualityResult, target_db: float) -> None:
    """Add the quality parameters of `result` to its cache layer."""
    add_parameters(
        result.layer,
        {
            "qualityChoice": format_params(result.point),
            "qualityTarget": float(target_db),
            "qualityPredicted": float(result.predicted_db),
            "qualityMeasured": float(result.measured_db),
            "qualityRawPsnr": float(result.raw_db),
            "qualityTargetMet": int(result.target_met),
            "qualityEnergyRatio": round(result.energy_ratio, 4),
            "qualityReferenceSpp": int(result.reference_spp),
            "qualityPilot": f"{result.pilot[0]}x{result.pilot[1]}",
            "qualityMeasuredSize": "{}x{}".format(*result.measured_size),
        },
    )


def add_parameters(layer: Path, added: dict[str, object]) -> None:
    """Add entries to a cache layer's parameters and re-hash them into its content hash."""
    description = read_cache_layer(layer)
    parameters = {**description.parameters, **added}
    write_cache_layer(
        layer,
        dataclasses.replace(
            description,
            parameters=parameters,
            content_hash=content_hash(description.inputs, parameters, description.code_version),
        ),
    )
