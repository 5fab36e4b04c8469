"""`relight bake --quality PSNR`: sizes chosen from pilot bakes meet the target on the Cornell box."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from pipeline.bake import quality
from pipeline.bake.direct.bake import bake_direct
from pipeline.bake.quality import (
    Measured,
    bake_for_quality,
    climb_at_full_size,
    corrected_psnr,
    measurement_window,
    pilot_size,
)
from pipeline.cli import main
from pipeline.reference.path_tracer import PathTracer, ReferenceImage, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES
from relight_torch.cache.layer import read_cache_layer
from relight_torch.direct.relighter import open_relighter
from relight_torch.metrics import psnr

TARGET_DB = 30.0


def test_direct_sized_for_a_target_meets_it_with_a_smaller_cache_than_the_default(tmp_path):
    bundled = SCENES["cornell_box"]
    shot = bundled.write(tmp_path / "scene")
    assert (
        main(
            [
                "bake",
                str(shot),
                "--camera",
                bundled.camera,
                "--width",
                "32",
                "--height",
                "32",
                "--out",
                str(tmp_path / "sized"),
                "--quality",
                str(TARGET_DB),
                "--method",
                "direct",
            ]
        )
        == 0
    )
    layer = tmp_path / "sized" / "cornell_box.relight.usda"
    description = read_cache_layer(layer)
    parameters = description.parameters
    assert parameters["qualityTarget"] == TARGET_DB and parameters["qualityPilot"] == "32x32"
    assert parameters["qualityMeasured"] >= TARGET_DB and math.isfinite(parameters["qualityPredicted"])
    assert parameters["qualityReferenceSpp"] >= 32
    assert not any(path.name.startswith(".") for path in layer.parent.iterdir())  # pilot bakes removed

    # An independent check: another seed, more spp, raw PSNR (the reference's noise not subtracted).
    scene = load_scene(shot, width=32, height=32)
    camera = find_camera(scene, bundled.camera)
    reference = PathTracer(scene, ReferenceSettings(spp=512, max_bounces=0, seed=7)).render(camera).mean
    assert psnr(open_relighter(layer).render().numpy(), reference) >= TARGET_DB

    # The simple scene needs fewer sub-samples than the default 2 x 2: a smaller cache.
    default = bake_direct(scene, camera, tmp_path / "default", "cornell_box")
    assert parameters["supersampling"] < 2
    assert sum(p.num_bytes for p in description.payloads) < sum(p.num_bytes for p in read_cache_layer(default).payloads)


def test_a_film_size_frame_is_measured_on_its_centre_window_and_baked_whole(tmp_path, monkeypatch):
    """Above MEASURE_PIXELS the full-size check measures the centre window at the frame's pixel
    density; the cache is still the whole frame, and it says what was measured."""
    monkeypatch.setattr(quality, "MEASURE_PIXELS", 24 * 16)
    bundled = SCENES["cornell_box"]
    shot = bundled.write(tmp_path / "scene")
    arguments = ["bake", str(shot), "--camera", bundled.camera, "--width", "48", "--height", "32"]
    arguments += ["--out", str(tmp_path / "sized"), "--quality", "25", "--method", "direct"]
    assert main(arguments) == 0
    description = read_cache_layer(tmp_path / "sized" / "cornell_box.relight.usda")
    assert description.resolution == (48, 32)
    assert description.parameters["qualityMeasuredSize"] == "24x16"
    assert math.isfinite(description.parameters["qualityMeasured"])
    assert not any(path.name.startswith(".") for path in (tmp_path / "sized").iterdir())


def test_a_choice_the_full_size_check_rejects_is_replaced_by_a_larger_size_measured_at_full_size(tmp_path):
    """The pilot's coarse pixels can pass a size the frame does not (on a 1080p exterior, 1,024
    gathers passed the pilot and measured about 34.5 dB on the window): the ladder's next sizes are
    measured at full size, not predicted again from the pilot. Here a pilot margin of -12 dB makes
    the pilot pick supersampling 1 for a 40 dB target; at 48 x 48 it measures about 38 dB, 2 about 42."""
    bundled = SCENES["cornell_box"]
    scene = load_scene(bundled.write(tmp_path / "scene"), width=48, height=48)
    camera = find_camera(scene, bundled.camera)
    result = bake_for_quality(
        scene, camera, tmp_path / "out", "cornell_box", "direct", 40.0, margin_db=-12.0, pilot_side=16
    )
    assert [c.point for c in result.candidates] == [{"supersampling": 1}]  # the pilot stopped at the first size
    assert result.point == {"supersampling": 2} and result.target_met and result.measured_db >= 40.0
    parameters = read_cache_layer(result.layer).parameters
    assert parameters["supersampling"] == 2 and parameters["qualityTargetMet"] == 1
    assert math.isnan(parameters["qualityPredicted"])  # never baked on the pilot
    assert not any(path.name.startswith(".") for path in (tmp_path / "out").iterdir())


def _measured(point: dict[str, object], db: float, num_bytes: float) -> Measured:
    return Measured(point, db, db, 1.0, num_bytes, Path("unused"), 0)


def test_the_climb_takes_the_cheapest_passing_variant_of_the_first_step_with_one_else_the_best():
    first = _measured({"gathers": 1, "coefficients": 50}, 34.0, 10)
    steps = [{"gathers": 1, "coefficients": (50, 100)}, {"gathers": 4, "coefficients": (50, 100)}, {"gathers": 16}]
    figures = {(1, 100): 34.5, (4, 50): 36.0, (4, 100): 37.0, (16, 50): 40.0}
    asked = []

    def measure(index: int, step: dict[str, object]) -> list[Measured]:
        asked.append(index)
        counts = step.get("coefficients", (50,))
        return [
            _measured(
                {"gathers": step["gathers"], "coefficients": c},
                figures.get((step["gathers"], c), 34.0),
                step["gathers"] * c,
            )
            for c in counts
        ]

    assert climb_at_full_size(first, steps, measure, 35.0).point == {"gathers": 4, "coefficients": 50}
    assert asked == [0, 1]  # stops at the first step with a passing variant
    assert climb_at_full_size(first, steps, measure, 41.0).point == {"gathers": 16, "coefficients": 50}  # the best
    assert climb_at_full_size(first, steps[:1], measure, 41.0).point == {"gathers": 1, "coefficients": 100}


def test_the_measurement_window_is_the_frame_up_to_its_pixel_cap(tmp_path):
    bundled = SCENES["cornell_box"]
    scene = load_scene(bundled.write(tmp_path), width=1920, height=1080)
    camera = find_camera(scene, bundled.camera)
    assert measurement_window(scene, camera, 1920 * 1080) == (scene, camera)
    windowed_scene, window = measurement_window(scene, camera, 640 * 480)
    assert (window.width, window.height) == (736, 408)  # multiples of 8, the aspect kept within 2 %
    assert windowed_scene.cameras[camera.path] == window and windowed_scene.geometry is scene.geometry


def test_pilot_size_keeps_the_aspect_and_never_grows():
    assert pilot_size(640, 480, 64) == (64, 48)
    assert pilot_size(32, 32, 64) == (32, 32)
    assert pilot_size(1000, 10, 50) == (50, 1)


def test_corrected_psnr_removes_the_reference_noise_on_average():
    rng = np.random.default_rng(0)
    truth = np.full((64, 64, 3), 0.5, np.float32)
    variance = np.full_like(truth, 1e-3)
    reference = ReferenceImage(
        truth + rng.normal(0.0, math.sqrt(1e-3), truth.shape).astype(np.float32), variance, 0.0, 1
    )
    image = truth + 0.01  # a true MSE of 1e-4: 40 dB
    corrected, raw = corrected_psnr(image, reference)
    assert raw == pytest.approx(10 * math.log10(1 / 1.1e-3), abs=0.2)
    assert corrected == pytest.approx(40.0, abs=1.0)
