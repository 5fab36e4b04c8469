"""The shot cache: the default bake, sized by measurement to relight the final frame.

`relight bake SHOT --camera CAM --out DIR` without `--method` bakes what the shot needs to match the
full-GI path tracer (every bounce) to a quality target, deciding by measurement at a pilot size:

1. Components. The direct light alone (the direct part's bake of step 3) is compared at full size
   (the frame, or its centre window) with the full-GI reference the sizes are then measured
   against; if it already reaches the target, the shot needs no indirect component. Otherwise the
   indirect light comes from the transfer method (Hasan et al. 2006): the direct light on diffuse
   gathers carried to the pixels by F (I + M + ... + M^(B-1)). Measured at full size, not on the
   pilot: a pilot of a whole frame holds its sky, a window its subject (on an exterior of 100
   teapots at 1920 x 1080, direct alone passed a 64 x 36 pilot at 36.1 dB).
2. Bounces. One pilot transfer bake keeps M; the series is evaluated term by term (B = 1 ... MAX_BOUNCES)
   and stops where the bounces not yet added, estimated from the geometric decay of the last two
   terms, would change the image by less than `BOUNCE_TAIL_FRACTION` of the target's error (MSE)
   and its mean by less than `ENERGY_FRACTION`.
3. Filtering. The direct part's pixel filtering (sub-samples per pixel side, material samples per
   sub-sample side) is measured at the full pixel density (on the frame's centre window when it is
   film-sized), where textures and normal maps alias as they will in the frame (the pilot's pixels
   cover several of the full frame's), against the 0-bounce
   reference (`direct_filtering`): material samples while they pay, then sub-samples until the
   direct part alone reaches `DIRECT_SHARE_DB` above the target. Material samples cost only bake
   time; sub-samples cost every edit S^2.
4. Sizes. `bake_for_quality` sizes the chosen method along its ladder against the full-GI reference
   (pilot), bakes it at full size and measures it there; where no size reaches the target, the best
   one is baked and the layer says so (qualityTargetMet = 0).

The layer is that method's cache (opened by its relighter), with the shot's choice recorded in its
parameters: shotComponents, shotBounces, shotBounceTailDb (the PSNR of the estimated rest, against
a peak of 1), shotFiltering and shotDirectPartDb (the direct part against the 0-bounce reference)
and the quality figures of `bake_for_quality`.
"""

from __future__ import annotations

import itertools
import logging
import math
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from pipeline.bake.methods import bake_method
from pipeline.bake.quality import (
    QualityResult,
    add_parameters,
    bake_for_quality,
    corrected_psnr,
    measurement_window,
    pilot_size,
    reference_for,
    resized,
)
from pipeline.bake.transfer.bake import TransferSettings
from pipeline.reference.path_tracer import FULL_FRAME_BOUNCES
from pipeline.scene.types import Camera, Scene
from relight_torch import open_cache
from relight_torch.lights.light import Light, LightKind
from relight_torch.metrics import psnr_from_mse

log = logging.getLogger(__name__)

MAX_BOUNCES = 24
"""The most indirect bounces the transfer series is evaluated to."""
SERIES_GATHERS = 4096
"""Gathers of the pilot's transfer bake whose series chooses the bounces (M's rows: one per gather)."""
BOUNCE_TAIL_FRACTION = 0.25
"""The bounces left out may add at most this fraction of the target's MSE."""
TRANSFER_LADDER: list[dict[str, object]] = [
    {"supersampling": 2, "gathers": gathers, "coefficients": (50, 100, 200, 400), "bounceCoefficients": 1024}
    for gathers in (1024, 4096, 16384)
]
"""The transfer sizes the shot tries, cheapest first. Supersampling 2: the pilot's edges alias at 1 (its pixels
are several of the full frame's); M keeps 1,024 coefficients per row, as its few rows (one per gather) cost
little and the chapter's 40 lose light at every bounce."""
DEFAULT_TARGET_DB = 35.0
MEASURE_HEADROOM_DB = 3.0
"""The full-size check's reference noise floor above the target: full-GI references are the bake's dearest
part, and the measured PSNR subtracts their noise (`quality.corrected_psnr`)."""
ENERGY_FRACTION = 0.005
"""The bounces left out may hold at most this fraction of the image's mean (the energy ratio's budget)."""
FILTER_LADDER: tuple[tuple[int, int], ...] = ((2, 2), (2, 4), (2, 8), (3, 8), (4, 8))
"""(supersampling, texture samples) of the direct part, cheapest relighting first: material samples cost
only bake time, so they grow first. Supersampling 2 at least: at 1 the edges alias. On the glossy scene
(brick albedo and normal map) at 160 x 120 the direct part alone against the 0-bounce reference was
30.7 / 33.3 / 34.9 dB for (2, 2) / (2, 4) / (2, 8) and 35.0 for (4, 2)."""
TEXTURE_GAIN_DB = 0.5
"""More material samples are taken only while doubling them gains at least this much under the probe
dome: an untextured shot's direct part does not change with them (only its light samples' noise differs)."""
PROBE_DOME = Light(path="/RelightShotProbe/Dome", kind=LightKind.DOME)
"""The uniform white dome `direct_filtering` also measures the direct part under (its intensity set there)."""
DIRECT_SHARE_DB = 3.0
"""The direct part's own PSNR must exceed the target by this much: half the target's MSE, the other half
left to the indirect part."""


@dataclass(frozen=True)
class ShotChoice:
    """What the pilot decided.

    Attributes:
        components: 'direct' or 'direct+transfer'.
        bounces: indirect bounces kept (0 for direct alone).
        direct_db: the direct light alone against the full-GI reference at full size (noise-corrected).
        tail_db: PSNR (peak 1) of the estimated change the bounces left out would make; inf when none.
        bounce_change_db: per added bounce b = 2 ... the PSNR of the change it made.
        filtering: (supersampling, texture samples) of the direct part (`choose_filtering`).
        direct_part_db: the direct part at full size against the 0-bounce reference (noise-corrected).
    """

    components: str
    bounces: int
    direct_db: float
    tail_db: float
    bounce_change_db: tuple[float, ...]
    filtering: tuple[int, int] = FILTER_LADDER[0]
    direct_part_db: float = math.nan


def choose_filtering(
    measure: Callable[[int, int], float], threshold_db: float, ladder: Sequence[tuple[int, int]] = FILTER_LADDER
) -> tuple[tuple[int, int], float]:
    """The first `ladder` point whose measured PSNR reaches `threshold_db`, else the best measured.

    Args:
        measure: (supersampling, texture samples) -> the direct part's PSNR (dB).
        threshold_db: the PSNR to reach.
        ladder: points to try, cheapest first.

    Returns:
        ((supersampling, texture samples), its PSNR).
    """
    best: tuple[tuple[int, int], float] | None = None
    for point in ladder:
        db = measure(*point)
        log.info("shot: direct part with supersampling %d, texture samples %d: %.2f dB", *point, db)
        if best is None or db > best[1]:
            best = (point, db)
        if db >= threshold_db:
            return point, db
    if best is None:
        raise ValueError("choose_filtering: empty ladder")
    return best


def direct_filtering(
    scene: Scene,
    camera: Camera,
    work: Path,
    stem: str,
    target_db: float,
    min_texture_samples: int,
    time_code: float | None,
) -> tuple[tuple[int, int], float, Path]:
    """`choose_filtering` on the shot at full size (its centre window, `quality.measurement_window`,
    for a film-size frame): direct bakes against 0-bounce references (noise `MEASURE_HEADROOM_DB`
    below the direct part's threshold), the ladder's material samples raised to at least
    `min_texture_samples`. Returns the chosen point, its PSNR and its direct bake (at full size).

    Two choices, each by the lighting that shows what it filters:
    - material samples: at the ladder's first supersampling, raised while they gain at least
      `TEXTURE_GAIN_DB` under one of two lightings, the shot's own lights and a uniform white dome
      (`PROBE_DOME`) as bright on average as they are, until both reach the threshold.
      Lights layers added after the bake (a dome over the glossy scene) light textures and normal
      maps the shot's lights leave dark or light from one side only: the glossy shot's key and spot
      passed with 2 x 2 x 4 x 4 samples per pixel (38.8 dB), and under the dome layer those gave
      33.3 dB;
    - supersampling: the ladder's first at those material samples that reaches the threshold
      under the shot's own lights. Supersampling costs every relight its square, and under the
      probe dome it bought light samples, not filtering: the closed Cornell box, dimly lit through
      its open side, took 3 x 3 for the dome's noise alone (a light move 215 against 140 ms).
    """
    threshold = target_db + DIRECT_SHARE_DB
    scene, camera = measurement_window(scene, camera)
    ladder = list(dict.fromkeys((s, max(t, min_texture_samples)) for s, t in FILTER_LADDER))
    layers: dict[tuple[int, int], Path] = {}

    def baked(supersampling: int, texture_samples: int) -> Path:
        if (supersampling, texture_samples) not in layers:
            layers[supersampling, texture_samples] = bake_method("direct").bake(
                scene,
                camera,
                work / f"filter-{supersampling}-{texture_samples}",
                stem,
                supersampling,
                texture_samples,
                time_code,
                None,
            )
        return layers[supersampling, texture_samples]

    shot_mean, dome_mean = _means_under_shot_and_probe(baked(*ladder[0]))
    lightings = [scene.lights]
    if dome_mean > 0 and shot_mean > 0:
        lightings.append([replace(PROBE_DOME, intensity=shot_mean / dome_mean)])
    references = [
        reference_for(replace(scene, lights=lights), camera, 0, threshold, MEASURE_HEADROOM_DB) for lights in lightings
    ]

    def measure(supersampling: int, texture_samples: int, count: int = len(lightings)) -> list[float]:
        """The point's PSNR under each of the first `count` lightings."""
        relighter = open_cache(baked(supersampling, texture_samples))
        figures = []
        for lights, reference in list(zip(lightings, references, strict=True))[:count]:
            relighter.set_lights(list(lights))
            figures.append(corrected_psnr(relighter.render().numpy(), reference)[0])
        return figures

    first = ladder[0][0]
    samples = choose_texture_samples(
        lambda texture_samples: measure(first, texture_samples),
        threshold,
        [t for s, t in ladder if s == first],
    )
    supersamplings = [(s, samples) for s in dict.fromkeys(s for s, _ in ladder)]
    point, db = choose_filtering(lambda s, t: measure(s, t, count=1)[0], threshold, supersamplings)
    return point, db, layers[point]


def _means_under_shot_and_probe(layer: Path) -> tuple[float, float]:
    """The mean of the cache's frame under its own lights and under `PROBE_DOME` at unit intensity.

    A function of its own so that the relighter is released before the next bake: a large shot's
    relighter holds gigabytes (docs/bench/exterior), which a bake beside it would add to."""
    relighter = open_cache(layer)
    shot_mean = float(relighter.render().mean())
    relighter.set_lights([PROBE_DOME])
    return shot_mean, float(relighter.render().mean())


def choose_texture_samples(
    measure: Callable[[int], Sequence[float]], threshold_db: float, options: Sequence[int]
) -> int:
    """The material samples of the direct part: `options` (increasing) taken in turn while the
    lowest measured PSNR is below `threshold_db` and the last step gained at least
    `TEXTURE_GAIN_DB` under some lighting (the lowest may be held down by what material samples do
    not filter: the probe dome's error at metal outlines).

    Args:
        measure: texture samples -> the direct part's PSNR (dB) under each lighting.
        threshold_db: the PSNR that needs no more.
        options: the texture samples to try, cheapest first.
    """
    chosen, chosen_db = options[0], list(measure(options[0]))
    for samples in options[1:]:
        if min(chosen_db) >= threshold_db:
            break
        db = list(measure(samples))
        log.info(
            "shot: direct part with texture samples %d: %s dB (%d: %s dB), under each lighting",
            samples,
            _decibels(db),
            chosen,
            _decibels(chosen_db),
        )
        if max(new - old for new, old in zip(db, chosen_db, strict=True)) < TEXTURE_GAIN_DB:
            break
        chosen, chosen_db = samples, db
    return chosen


def _decibels(figures: Sequence[float]) -> str:
    return " / ".join(f"{figure:.2f}" for figure in figures)


def choose_bounces(images: list[np.ndarray], target_db: float) -> tuple[int, float, tuple[float, ...]]:
    """The fewest bounces whose left-out rest is negligible against the target.

    The rest after n bounces is the difference to the last image plus, beyond it, the geometric
    continuation of the last two terms' decay; it must stay under `BOUNCE_TAIL_FRACTION` of the
    target's MSE and hold at most `ENERGY_FRACTION` of the image's mean.

    Args:
        images: (H, W, 3) renders with 1, 2, ..., N bounces (N >= 2).
        target_db: the quality target (PSNR, peak 1).

    Returns:
        (bounces, PSNR (peak 1) of the estimated rest, PSNR of the change each bounce 2 ... N made).
    """
    budget = BOUNCE_TAIL_FRACTION * 10.0 ** (-target_db / 10.0)
    changes = [after - before for before, after in itertools.pairwise(images)]
    rms = [float(np.sqrt(np.mean(change**2))) for change in changes]
    ratio = min(rms[-1] / rms[-2], 0.99) if len(rms) > 1 and rms[-2] > 0 else 0.0
    beyond = changes[-1] * (ratio / (1.0 - ratio))
    change_db = tuple(psnr_from_mse(max(r * r, 1e-20)) for r in rms)
    rests = [images[-1] - image + beyond for image in images]
    rest_mse = [float(np.mean(rest**2)) for rest in rests]
    energy = ENERGY_FRACTION * float(np.mean(images[-1] + beyond))
    bounces = next(
        (
            n
            for n, (mse, rest) in enumerate(zip(rest_mse, rests, strict=True), start=1)
            if mse <= budget and float(np.mean(rest)) <= energy
        ),
        len(images),
    )
    return bounces, psnr_from_mse(max(rest_mse[bounces - 1], 1e-20)), change_db


def choose_components(
    scene: Scene,
    camera: Camera,
    work: Path,
    stem: str,
    target_db: float,
    texture_samples: int,
    time_code: float | None,
    pilot_side: int,
    filtering: tuple[int, int],
    direct_db: float,
) -> ShotChoice:
    """Direct alone where its full-size PSNR against the full frame, `direct_db`, reaches the
    target; otherwise the transfer series measured bounce by bounce on the pilot."""
    log.info("shot: direct alone %.2f dB against the full frame at full size", direct_db)
    if direct_db >= target_db:
        return ShotChoice("direct", 0, direct_db, float("inf"), (), filtering)
    width, height = pilot_size(camera.width, camera.height, pilot_side)
    pilot_scene, pilot_camera = resized(scene, camera, width, height)
    settings = TransferSettings(
        num_gathers=SERIES_GATHERS, num_bounces=MAX_BOUNCES, num_coefficients=200, num_bounce_coefficients=1024
    )
    layer = bake_method("transfer").bake(
        pilot_scene, pilot_camera, work / "transfer", stem, 1, texture_samples, time_code, settings
    )
    relighter = open_cache(layer)
    images = []
    for bounces in range(1, MAX_BOUNCES + 1):
        relighter.num_bounces = bounces
        relighter.invalidate_indirect()
        images.append(relighter.render().numpy())
    bounces, tail_db, change_db = choose_bounces(images, target_db)
    if bounces == MAX_BOUNCES:
        log.warning(
            "shot: %d bounces leave light out (the rest estimated at %.1f dB against a %g dB target)",
            bounces,
            tail_db,
            target_db,
        )
    log.info(
        "shot pilot %dx%d: %d bounces (rest estimated at %.1f dB; changes %s)",
        width,
        height,
        bounces,
        tail_db,
        ", ".join(f"{db:.1f}" for db in change_db),
    )
    return ShotChoice("direct+transfer", bounces, direct_db, tail_db, change_db, filtering)


def bake_shot(
    scene: Scene,
    camera: Camera,
    out_dir: str | Path,
    stem: str,
    target_db: float = DEFAULT_TARGET_DB,
    texture_samples: int = 2,
    time_code: float | None = None,
    pilot_side: int = 64,
) -> tuple[ShotChoice, QualityResult]:
    """Bake the shot cache of `scene` seen by `camera` for `target_db` against the full frame.

    `texture_samples` is the least material filtering of the direct part; the shot raises it (and the
    supersampling) where its textures need more (`direct_filtering`).

    Returns:
        (the pilot's choice, the sizing result of `bake_for_quality`, whose layer is the cache).

    A shot none of whose sizes reaches the target (a tiny image: its pixels are too coarse for any
    size) is baked at the best size of the ladder, with a warning and `qualityTargetMet` = 0.
    """
    out_dir = Path(out_dir)
    work = out_dir / f".{stem}.shot-pilot"
    try:
        filtering, direct_part_db, direct_layer = direct_filtering(
            scene, camera, work, stem, target_db, texture_samples, time_code
        )
        window_scene, window = measurement_window(scene, camera)
        full_reference = reference_for(window_scene, window, FULL_FRAME_BOUNCES, target_db, MEASURE_HEADROOM_DB)
        direct_db, _ = corrected_psnr(open_cache(direct_layer).render().numpy(), full_reference)
        choice = choose_components(
            scene, camera, work, stem, target_db, filtering[1], time_code, pilot_side, filtering, direct_db
        )
    finally:
        shutil.rmtree(work, ignore_errors=True)
    choice = replace(choice, direct_part_db=direct_part_db)
    supersampling, texture_samples = filtering
    if choice.components == "direct":
        method, fixed, ladder = "direct", None, None
    else:
        method, fixed = "transfer", {"bounces": choice.bounces}
        ladder = [{**step, "supersampling": supersampling} for step in TRANSFER_LADDER]
    result = bake_for_quality(
        scene,
        camera,
        out_dir,
        stem,
        method,
        target_db,
        1,
        texture_samples,
        time_code,
        fixed=fixed,
        pilot_side=pilot_side,
        reference_bounces=FULL_FRAME_BOUNCES,
        ladder=ladder,
        measure_headroom_db=MEASURE_HEADROOM_DB,
        best_effort=True,
        full_reference=full_reference,
    )
    _record(result.layer, choice)
    return choice, result


def _record(layer: Path, choice: ShotChoice) -> None:
    """Add the shot's choice to the cache layer's parameters."""
    add_parameters(
        layer,
        {
            "shotComponents": choice.components,
            "shotBounces": choice.bounces,
            "shotDirectDb": round(choice.direct_db, 2),
            "shotBounceTailDb": round(choice.tail_db, 2),
            "shotBounceChangesDb": ", ".join(f"{db:.1f}" for db in choice.bounce_change_db),
            "shotFiltering": "supersampling={}, textureSamples={}".format(*choice.filtering),
            "shotDirectPartDb": round(choice.direct_part_db, 2),
        },
    )
