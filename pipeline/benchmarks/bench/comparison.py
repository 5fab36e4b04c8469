"""What a user would compare a relighting method with: re-rendering with the reference path tracer.

The path tracer's error falls as 1/spp. Against the bench's reference (N spp, its generator seeded with zero), a
render of s spp (seeded otherwise, so its noise is independent) has

    MSE(s) = a (1/s + 1/N)

a being the per-sample variance of a pixel. `measure_spp_curve` renders the shot at a few low spp
and takes a as the median of the per-render estimates MSE(s) / (1/s + 1/N): clamping to [0, 1]
trims fireflies at 1 spp, which lowers that render's estimate (by ~30 % with one bounce on the
Cornell box; at 2..16 spp they agree within ~10 %), and the median ignores it. The render time is
fitted as fixed + per_spp * s over the low-spp renders, each rendered again in this run even when
cached (the reference's time may come from an earlier run under another load, and the methods'
relight times are taken in this one). From it, per method point (light edit 'shot', where
relight_ms is measured):

    reference-equal-time   the spp that fits in the method's relight time (per_spp only: the
                           fixed cost is not charged, which favours the path tracer) and the
                           PSNR the fit predicts at that spp (extrapolated below the measured spp)
    reference-full         the spp the path tracer needs to reach the method's PSNR, its time
                           (again per_spp only) and speedup = that time / the method's relight
                           time. The method's own error is its MSE less the reference's a/N; where
                           that is <= 0 the method is indistinguishable from the reference at N
                           spp and the row is a lower bound (spp = N, bound=lower).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.bake.adapter import format_params
from pipeline.benchmarks.bench.references import References
from pipeline.benchmarks.rows import NAN, SweepRow
from relight_torch.metrics import psnr, psnr_from_mse

CURVE_SEED = 1
"""Seed of the low-spp renders' generator (the reference's is seeded with zero: their noise must be independent)."""


@dataclass(frozen=True)
class SppCurve:
    """The path tracer's error and time against spp on one scene's shot.

    Attributes:
        bounces: indirect bounces of the renders.
        spp, seconds, mse: the measured low-spp renders (MSE of clamped images against the reference).
        reference_spp, reference_seconds: the reference's spp and render time.
        noise: a, the per-sample variance (MSE x spp): the median of the renders' estimates.
        seconds_per_spp, seconds_fixed: the fitted render time per spp and per render.
    """

    bounces: int
    spp: tuple[int, ...]
    seconds: tuple[float, ...]
    mse: tuple[float, ...]
    reference_spp: int
    reference_seconds: float
    noise: float
    seconds_per_spp: float
    seconds_fixed: float

    def mse_at(self, spp: float) -> float:
        """Predicted MSE against the reference of an `spp` render."""
        return self.noise * (1.0 / spp + 1.0 / self.reference_spp)

    def spp_for(self, mse: float) -> float:
        """spp whose own error (without the reference's noise) equals that of an image with `mse`
        against the reference; inf when `mse` is within the reference's noise."""
        own = mse - self.noise / self.reference_spp
        return self.noise / own if own > 0 else math.inf


def measure_spp_curve(references: References, bounces: int, spp: tuple[int, ...]) -> SppCurve:
    """Render the shot at each of `spp` (seed CURVE_SEED, timed now) and fit `SppCurve` (see the
    module doc); with a single count, its time is all per-spp."""
    reference = references.render("shot", bounces)
    renders = [references.render("shot", bounces, count, CURVE_SEED, fresh=True) for count in spp]
    mse = np.array([10 ** (-psnr(render.mean, reference.mean) / 10) for render in renders])
    noise = float(np.median(mse / (1.0 / np.asarray(spp, float) + 1.0 / references.spp)))
    seconds = np.asarray([render.seconds for render in renders])
    counts = np.asarray(spp, float)
    per_spp, fixed = np.polyfit(counts, seconds, 1) if len(set(spp)) > 1 else (seconds.mean() / counts[0], 0.0)
    return SppCurve(
        bounces,
        tuple(spp),
        tuple(float(s) for s in seconds),
        tuple(float(m) for m in mse),
        references.spp,
        reference.seconds,
        noise,
        max(float(per_spp), 1e-12),
        float(fixed),
    )


def comparison_rows(rows: list[SweepRow], curves: dict[tuple[str, int], SppCurve]) -> list[SweepRow]:
    """The reference-equal-time and reference-full rows of every timed method row (see the module doc).

    Args:
        rows: method rows; those of light edit 'shot' with a finite relight_ms are compared.
        curves: (scene, bounces) -> the path tracer's curve at the rows' bounce count.
    """
    out = []
    for row in rows:
        if row.light_edit != "shot" or not math.isfinite(row.relight_ms):
            continue
        curve = curves[(row.scene, int(row.parameters()["bounces"]))]
        base = {"vs": row.method, **row.parameters()}
        equal_spp = row.relight_ms / 1e3 / curve.seconds_per_spp
        out.append(
            SweepRow(
                "reference-equal-time",
                row.scene,
                row.width,
                row.height,
                row.light_edit,
                format_params({**base, "spp": f"{equal_spp:.4g}"}),
                psnr_from_mse(curve.mse_at(equal_spp)),
                NAN,
                NAN,
                NAN,
                NAN,
                row.relight_ms,
                "cpu",
            )
        )
        needed = curve.spp_for(10 ** (-row.psnr_db / 10))
        bound = "lower" if math.isinf(needed) else "fit"
        needed = curve.reference_spp if math.isinf(needed) else needed
        full_ms = 1e3 * needed * curve.seconds_per_spp
        out.append(
            SweepRow(
                "reference-full",
                row.scene,
                row.width,
                row.height,
                row.light_edit,
                format_params(
                    {**base, "spp": f"{needed:.4g}", "bound": bound, "speedup": f"{full_ms / row.relight_ms:.4g}"}
                ),
                row.psnr_db,
                NAN,
                NAN,
                NAN,
                NAN,
                full_ms,
                "cpu",
            )
        )
    return out


def summary(rows: list[SweepRow]) -> str:
    """One line per (scene, method): its point with the largest speed-up over the path tracer at
    equal PSNR, with the path tracer's PSNR in the method's time beside it."""
    lines = [
        f"{'scene':12} {'method':10} {'PSNR dB':>8} {'relight ms':>11} {'tracer spp':>11} {'tracer ms':>11} "
        f"{'speed-up':>9} {'tracer dB at equal time':>24}  params"
    ]
    full = [r for r in rows if r.method == "reference-full"]
    for key in dict.fromkeys((r.scene, r.parameters()["vs"]) for r in full):
        best = max(
            (r for r in full if (r.scene, r.parameters()["vs"]) == key), key=lambda r: float(r.parameters()["speedup"])
        )
        parameters = best.parameters()
        method_params = best.params.split(" spp=")[0]
        equal = next(
            r
            for r in rows
            if r.method == "reference-equal-time"
            and r.scene == best.scene
            and r.params.split(" spp=")[0] == method_params
        )
        bound = ">=" if parameters["bound"] == "lower" else ""
        lines.append(
            f"{best.scene:12} {key[1]:10} {best.psnr_db:8.2f} {equal.relight_ms:11.1f} "
            f"{bound + parameters['spp']:>11} {best.relight_ms:11.0f} {bound + parameters['speedup'] + 'x':>9} "
            f"{equal.psnr_db:24.2f}  {method_params.split(' ', 1)[1]}"
        )
    return "\n".join(lines)
