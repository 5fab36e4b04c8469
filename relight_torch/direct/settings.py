"""The direct relighter's settings: sampling, the visibility filter, memory and shared light."""

from __future__ import annotations

import os
from dataclasses import dataclass


@dataclass(frozen=True)
class RelightSettings:
    """Sampling of the relighter.

    Attributes:
        area_samples: fixed samples per shading point for sphere, rect, disk, cylinder and distant
            lights with an angle (delta lights take one).
        dome_samples: fixed samples per shading point for dome lights, half of them drawn from
            the BRDF's glossy lobes (`direct.brdf_samples`).
        seed: seed of the per-point sample rotations.
        chunk_samples: light samples processed together (bounds the (N, S, 3) temporaries).
        full_sampling_angle: angular radius (degrees) from which a light gets all `area_samples`;
            smaller lights get fewer, in proportion to their solid angle
            (`light_samples.adaptive_sample_count`). 0 gives every light `area_samples`.
        min_area_samples: the fewest samples a small light gets.
        shadow_map_resolution: texels per side of each shadow-map face (`shadows='shadowmaps'`);
            512 builds ~5x faster than 1024 with the 'pcss' lookup within 0.3 dB of it on the
            Cornell box (`pipeline.benchmarks.shadow_map_accuracy`).
        shadow_map_lookup: 'pcss' (at most three depth reads per shadow ray) or 'march' (the
            exact march of `shadow_map_march_steps` reads), see `visibility.shadow_maps`.
        shadow_map_march_steps: depth-map reads per shadow ray of the 'march' lookup.
        shadow_filter_radius: r in sub-samples of the same-surface box filter
            (`visibility.surface_filter`, 2r + 1 taps per pass) over the shadowed and unshadowed
            estimates of lights with a closed-form irradiance (the ratio estimator's denoised
            visibility); 0: no filter; None: sized from the image (`auto_filter_radius`). It pays
            where penumbrae span many pixels and samples are few (Cornell box 640x480, 1 sample:
            35.7 -> 45.0 dB at r = 4) and blurs where they do not (64x64 with 16 samples: -1.3 to
            -1.6 dB at r = 2).
        filtered_area_samples: samples per matte shading point of a light whose visibility is
            filtered (the filter averages (2r + 1)^2 neighbours' samples); glossy points
            (`preview_surface.glossy`) keep `area_samples`: the filter denoises the diffuse term
            only, not highlights (the set at 640x480, against 64 samples: 1 filtered at matte
            points and 16 at glossy ones 38.5 dB, 1 everywhere 34.8, 16 unfiltered 37.9).
        memory_budget: bytes the per-light caches (transports and unit images, `cache_bytes`)
            may hold between renders; None: MEMORY_BUDGET_FRACTION of the machine's memory
            (`default_memory_budget`). Over it, the relighter drops the transports of the lights
            edited longest ago (a later shaping edit of one traces it again), makes a light's
            images tile by tile without keeping its transport when that would not fit, then folds
            the unit images of the lights edited longest ago into one (N, 3) sum (the frame is
            unchanged; editing a folded light traces it again), and last keeps unit images in half
            precision (a relative rounding of 2^-11, far below the light samples' noise). The
            G-buffer, the BVH, the sum of the lights not being edited and one frame's temporaries
            are outside it.
        shared_lighting: the sub-samples of a pixel on one surface share one evaluation of each
            light (`direct.sharing`): its samples, shadow rays and BRDF factors, combined with each
            sub-sample's own material; False evaluates every sub-sample (supersampling 1 always
            does). Lights whose radiance is not one colour times a scalar (textured lights,
            coloured shadows) are always evaluated per sub-sample.
    """

    area_samples: int = 16
    dome_samples: int = 64
    seed: int = 0
    chunk_samples: int = 1 << 20
    full_sampling_angle: float = 0.0
    min_area_samples: int = 1
    shadow_map_resolution: int = 512
    shadow_map_lookup: str = "pcss"
    shadow_map_march_steps: int = 16
    shadow_filter_radius: int | None = None
    filtered_area_samples: int = 1
    memory_budget: int | None = None
    shared_lighting: bool = True


MEMORY_BUDGET_FRACTION = 1 / 24
"""Share of the machine's physical memory the per-light caches get by default: on a 24 GB machine
1 GB, which keeps a relighter of a 1920x1080 shot of tens of millions of occluder triangles within
8 GB (the BVH, the G-buffer and a frame's temporaries are the rest: docs/ARCHITECTURE.md, Measuring)."""


def default_memory_budget() -> int:
    """MEMORY_BUDGET_FRACTION of this machine's physical memory, in bytes."""
    return int(MEMORY_BUDGET_FRACTION * os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


AUTO_FILTER_MIN_PIXELS = 240
"""Shorter image side (pixels) from which `auto_filter_radius` filters visibility."""
AUTO_FILTER_PIXELS_PER_TAP = 120
AUTO_FILTER_MAX_RADIUS = 4


def auto_filter_radius(image_size: tuple[int, int], supersampling: int) -> int:
    """The visibility filter's radius in sub-samples for a sub-sample image (H, W) when
    `RelightSettings.shadow_filter_radius` is None.

    One pixel of radius per AUTO_FILTER_PIXELS_PER_TAP pixels of the shorter side, at most
    AUTO_FILTER_MAX_RADIUS, and none below AUTO_FILTER_MIN_PIXELS, where penumbrae span few
    pixels and 16 unfiltered samples stay cheap: 640x480 -> 4 pixels (1 sample: 45.2 dB on the
    Cornell box, 16 unfiltered: 45.3), 400x400 -> 3, 160x160 -> 0.
    """
    pixels = min(image_size) // supersampling
    if pixels < AUTO_FILTER_MIN_PIXELS:
        return 0
    return supersampling * min(AUTO_FILTER_MAX_RADIUS, pixels // AUTO_FILTER_PIXELS_PER_TAP)
