"""The transfer method end to end on a small Cornell box, against the reference path tracer.

One bake (32 x 32 pixels, 1,024 gathers, 100 + 40 coefficients, two bounces) shared by the tests.
The thresholds are the figures measured when the test was written, less ~1 dB for the
references' Monte Carlo noise (256 paths per pixel); the indirect part is biased low by ~10 % at
this gather count (discretisation, clamp and wavelet culling), which the mean-ratio bounds record.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from pipeline.bake.transfer.bake import TransferSettings, bake_transfer
from pipeline.cli import main
from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import cornell_box
from relight_torch import open_cache
from relight_torch.cache.layer import read_cache_layer
from relight_torch.direct.relighter import Relighter
from relight_torch.io.exr import read_exr
from relight_torch.lights.light import Light, LightKind, Shaping
from relight_torch.metrics import psnr
from relight_torch.transfer.open import open_transfer_relighter
from relight_torch.transfer.relighter import TransferRelighter, wavelet_light
from relight_torch.transfer.sparse import column_norms
from relight_torch.upsample import edge_aware_upsampler

SIZE = 32


@pytest.fixture(scope="module")
def cornell(tmp_path_factory):
    directory = tmp_path_factory.mktemp("cornell_transfer")
    path = cornell_box.write(directory)
    scene = load_scene(path, width=SIZE, height=SIZE)
    camera = find_camera(scene, cornell_box.CAMERA)
    settings = TransferSettings(num_gathers=1024, num_coefficients=100, num_bounces=2, num_bounce_coefficients=40)
    layer = bake_transfer(
        scene,
        camera,
        directory / "cache",
        "cornell",
        supersampling=1,
        texture_samples=1,
        settings=settings,
        progress=False,
    )
    references = {
        b: PathTracer(scene, ReferenceSettings(spp=256, max_bounces=b)).render(camera).mean for b in (0, 1, 2)
    }
    return layer, references, scene, camera


def _one_bounce(relighter: TransferRelighter) -> TransferRelighter:
    return TransferRelighter(relighter.direct, relighter.gathers, relighter.view_pixels, relighter.final_gather)


@pytest.mark.parametrize("bounces, full_db, indirect_db", [(1, 30.5, 35.0), (2, 29.5, 33.5)])
def test_matches_the_path_tracer_with_the_same_bounces(cornell, bounces, full_db, indirect_db):
    layer, references, _, _ = cornell
    relighter = open_cache(layer)
    assert isinstance(relighter, TransferRelighter) and relighter.num_bounces == 2
    if bounces == 1:
        relighter = _one_bounce(relighter)
    image, indirect = relighter.render().numpy(), relighter.indirect_image().numpy()
    reference_indirect = references[bounces] - references[0]
    assert np.isfinite(image).all()
    assert psnr(image, references[bounces]) >= full_db
    assert psnr(indirect, reference_indirect) >= indirect_db
    ratio = indirect.mean() / reference_indirect.mean()
    assert 0.8 <= ratio <= 1.05
    # Without the indirect part the image is far further from the reference.
    assert psnr(relighter.direct.render().numpy(), references[bounces]) < psnr(image, references[bounces]) - 3.0


def test_light_edits_recompute_only_what_they_touch(cornell):
    layer, _, _, _ = cornell
    relighter = open_cache(layer)
    before = relighter.indirect_image()
    assert relighter.counters["gather_light"] == 1
    light = relighter.lights[0]
    relighter.set_light(dataclasses.replace(light, intensity=light.intensity * 2.0))
    brighter = relighter.indirect_image()
    assert relighter.counters["gather_light"] == 1  # a colour edit is a rescale
    np.testing.assert_allclose(brighter.numpy(), 2.0 * before.numpy(), rtol=1e-5, atol=1e-7)
    moved = light.world_from_light.copy()
    moved[0, 3] -= 100.0
    relighter.set_light(dataclasses.replace(light, world_from_light=moved))
    shifted = relighter.indirect_image()
    assert relighter.counters["gather_light"] == 2
    assert not np.allclose(shifted.numpy(), before.numpy())


def test_direct_caches_still_open_as_direct(tmp_path):
    path = cornell_box.write(tmp_path)
    out = tmp_path / "direct"
    assert (
        main(
            [
                "bake",
                str(path),
                "--camera",
                cornell_box.CAMERA,
                "--out",
                str(out),
                "--width",
                "8",
                "--height",
                "8",
                "--method",
                "direct",
            ]
        )
        == 0
    )
    relighter = open_cache(out / "cornell_box.relight.usda")
    assert isinstance(relighter, Relighter)
    assert relighter.supersampling == 2  # the direct method's default (transfer's is 1: below)


def test_cli_bakes_and_renders_a_quantised_transfer_cache(tmp_path):
    path = cornell_box.write(tmp_path)
    out = tmp_path / "cache"
    assert (
        main(
            [
                "bake",
                str(path),
                "--camera",
                cornell_box.CAMERA,
                "--out",
                str(out),
                "--width",
                "16",
                "--height",
                "16",
                "--method",
                "transfer",
                "--gathers",
                "256",
                "--coefficients",
                "30",
                "--quantize",
                "--indirect-scale",
                "2",
            ]
        )
        == 0
    )
    assert read_cache_layer(out / "cornell_box.relight.usda").supersampling == 1  # transfer's default
    assert not list(out.glob(".cornell_box.transfer-*"))  # the resumable chunks are cleaned up
    assert np.load(out / "cornell_box.viewPixels.npy").max() < 8 * 8
    assert np.load(out / "cornell_box.finalGatherValues.npy").dtype == np.uint8
    assert np.load(out / "cornell_box.finalGatherIndices.npy").dtype == np.uint16
    exr = tmp_path / "render.exr"
    assert main(["render", str(out / "cornell_box.relight.usda"), "-o", str(exr)]) == 0
    channels, _ = read_exr(exr)
    image = np.stack([channels[c] for c in ("R", "G", "B")], axis=-1)
    assert np.isfinite(image).all() and image.mean() > 0
    for bad in (["--gathers", "100"], ["--width", "16", "--height", "16", "--indirect-scale", "3"]):
        assert (
            main(["bake", str(path), "--camera", cornell_box.CAMERA, "--out", str(out), "--method", "transfer", *bad])
            != 0
        )


def _light_at(light: Light, kind: LightKind, position, emit_direction, **fields) -> Light:
    """`light` made a `kind` light at `position` (scene mm) emitting along world `emit_direction`."""
    local_z = -np.asarray(emit_direction, float)
    helper = np.array([0.0, 1.0, 0.0]) if abs(local_z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    local_x = np.cross(helper, local_z)
    local_x /= np.linalg.norm(local_x)
    world_from_light = np.eye(4)
    world_from_light[:3, :3] = np.stack([local_x, np.cross(local_z, local_x), local_z], axis=1)
    world_from_light[:3, 3] = position
    return dataclasses.replace(light, kind=kind, world_from_light=world_from_light, **fields)


# Where the method fails, measured when the test was written (32 x 32, 1,024 gathers, 2 bounces,
# 128-path references): a lamp 10 mm from the back wall, facing it, throws a hot spot a few gathers
# wide (full image 18.8 dB, indirect 20.5 dB against ~35 dB with the ceiling lamp; indirect mean
# 0.95 of the reference; 1.03 since the rect's closed form reaches the gathers), and a 3-degree
# spot light covers ~2 gathers of the floor, which the gathers' point-sampled irradiance mostly
# misses (34.6 and 38.2 dB only because that indirect light is dim; indirect mean 0.51 of the
# reference at the default 4 light samples per gather, 0.32 / 0.34 / 0.42 at 1 / 16 / 64: the two
# gathers' sampled irradiance decides it). Since the F rows are refitted to transfer the shot's
# ceiling lamp exactly (`relight_torch.transfer.responses`), lights far from it get its correction
# too: the lamp at the wall 19.2 / 20.8 dB with an indirect mean of 1.11 of the reference, the spot
# 35.5 / 40.6 dB and 0.65. Bounds: the measured figures less ~1.5 dB, and the mean ratio as
# measured +- ~0.15 (an improvement should move them).
FAILURES = {
    "lamp_at_wall": (
        dict(kind=LightKind.RECT, position=(278.0, 274.0, 549.2), emit_direction=(0.0, 0.0, 1.0)),
        17.5,
        19.0,
        (0.95, 1.25),
    ),
    "narrow_spot": (
        dict(
            kind=LightKind.SPHERE,
            position=(278.0, 540.0, 280.0),
            emit_direction=(0.0, -1.0, 0.0),
            radius=5.0,
            intensity=4e4,
            shaping=Shaping(cone_angle=3.0),
        ),
        33.0,
        36.5,
        (0.5, 0.8),
    ),
}


@pytest.mark.parametrize("case", sorted(FAILURES))
def test_failure_cases_stay_finite_with_a_measured_error(cornell, case):
    layer, _, scene, camera = cornell
    placement, full_db, indirect_db, (low_ratio, high_ratio) = FAILURES[case]
    relighter = open_cache(layer)
    light = _light_at(relighter.lights[0], **placement)
    relighter.set_lights([light])
    image, indirect = relighter.render().numpy(), relighter.indirect_image().numpy()
    edited = dataclasses.replace(scene, lights=[light])
    full, direct = (PathTracer(edited, ReferenceSettings(spp=128, max_bounces=b)).render(camera).mean for b in (2, 0))
    assert np.isfinite(image).all() and np.isfinite(indirect).all() and (indirect >= 0).all()
    assert psnr(image, full) >= full_db
    assert psnr(indirect, full - direct) >= indirect_db
    assert low_ratio <= indirect.mean() / (full - direct).mean() <= high_ratio


def test_one_gather_sample_adds_noise_that_the_final_gather_averages(cornell):
    layer, _, _, _ = cornell
    relighter = open_cache(layer)
    default = relighter.indirect_image().numpy()
    sparse = (
        TransferRelighter(
            relighter.direct,
            relighter.gathers,
            relighter.view_pixels,
            relighter.final_gather,
            relighter.bounce,
            relighter.num_bounces,
            gather_samples=1,
        )
        .indirect_image()
        .numpy()
    )
    relative_rms = np.sqrt(np.mean((sparse - default) ** 2) / np.mean(default**2))
    assert 0.0 < relative_rms < 0.1
    with pytest.raises(ValueError, match="gather_samples"):
        TransferRelighter(
            relighter.direct, relighter.gathers, relighter.view_pixels, relighter.final_gather, gather_samples=0
        )


def test_culling_weak_wavelet_lights_stays_within_its_bound(cornell):
    layer, references, _, _ = cornell
    exact = open_cache(layer)
    culled = open_transfer_relighter(layer, cull_tolerance=0.05)
    light = exact.lights[0]
    exact._unit_indirect(light)
    radiance = exact._per_light[light.path].radiance  # F multiplies g_d + M g_d (two bounces)
    light_vector = wavelet_light(radiance, exact.bounce, 2, exact.gathers.side)
    weights = light_vector.norm(dim=-1) * column_norms(exact.final_gather)
    difference = culled._unit_indirect(light) - exact._unit_indirect(light)
    assert 0.0 < float(difference.norm()) <= 0.05 * float(weights.sum())
    # Measured when written: tolerance 0.05 moved the unit indirect light by 1.2 % (L2; 0.002 of the
    # summed weights, the bound 0.05) and the indirect PSNR against the reference by -0.02 dB.
    reference = references[2] - references[0]
    loss = psnr(exact.indirect_image().numpy(), reference) - psnr(culled.indirect_image().numpy(), reference)
    assert abs(loss) < 0.3


def test_reduced_resolution_indirect_is_upsampled_along_edges(cornell, tmp_path):
    _, references, scene, camera = cornell
    settings = TransferSettings(num_gathers=1024, num_coefficients=100, indirect_scale=2)
    layer = bake_transfer(
        scene, camera, tmp_path, "cornell", supersampling=1, texture_samples=1, settings=settings, progress=False
    )
    relighter = open_transfer_relighter(layer)
    assert relighter.final_gather.num_rows <= (SIZE // 2) ** 2 and relighter.upsampler is not None
    reference = references[1] - references[0]
    indirect = relighter.indirect_image().numpy()
    assert np.isfinite(indirect).all()
    plain = TransferRelighter(
        relighter.direct,
        relighter.gathers,
        relighter.view_pixels,
        relighter.final_gather,
        upsampler=edge_aware_upsampler(
            relighter.direct.gbuffer,
            1,
            2,
            relighter.view_pixels,
            *(
                torch.from_numpy(np.load(tmp_path / f"cornell.view{name}.npy"))
                for name in ("Position", "Normal", "ObjectId")
            ),
            guided=False,
        ),
    )
    # Measured when written (32 x 32, 1,024 gathers, k = 100, F for 16 x 16): 37.9 dB, and 36.3 dB
    # with a plain tent filter that blends across edges. With the F rows refitted to the shot's
    # lamp (`relight_torch.transfer.responses`) both filters give 38.0 dB at this size: the tent's
    # loss came with the truncated rows' error, not the silhouettes. The edge-aware filter must stay
    # at least as good.
    assert psnr(indirect, reference) >= 37.0
    assert psnr(indirect, reference) >= psnr(plain.indirect_image().numpy(), reference) - 0.2
    # The light-group AOVs (direct and upsampled indirect per group) still sum to the beauty.
    groups = relighter.light_group_images()
    assert sorted(groups) == ["CeilingLight_direct", "CeilingLight_indirect"]
    np.testing.assert_allclose(
        (sum(groups.values()) + relighter.emission_image()).numpy(), relighter.render().numpy(), rtol=1e-5, atol=1e-7
    )
