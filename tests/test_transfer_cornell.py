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

from pipeline.bake.transfer.bake import TransferSettings, bake_transfer
from pipeline.cli import main
from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import cornell_box
from relight_torch.io.exr import read_exr
from relight_torch.metrics import psnr
from relight_torch.relighter import Relighter
from relight_torch.transfer.open import open_cache_relighter
from relight_torch.transfer.relighter import TransferRelighter

SIZE = 32


@pytest.fixture(scope="module")
def cornell(tmp_path_factory):
    directory = tmp_path_factory.mktemp("cornell_transfer")
    path = cornell_box.write(directory)
    scene = load_scene(path, width=SIZE, height=SIZE)
    camera = find_camera(scene, cornell_box.CAMERA)
    settings = TransferSettings(num_gathers=1024, num_coefficients=100, num_bounces=2, num_bounce_coefficients=40)
    layer = bake_transfer(scene, camera, directory / "cache", "cornell", supersampling=1, texture_samples=1,
                          settings=settings, progress=False)
    references = {b: PathTracer(scene, ReferenceSettings(spp=256, max_bounces=b)).render(camera).mean
                  for b in (0, 1, 2)}
    return layer, references


def _one_bounce(relighter: TransferRelighter) -> TransferRelighter:
    return TransferRelighter(relighter.direct, relighter.gathers, relighter.view_pixels, relighter.final_gather)


@pytest.mark.parametrize("bounces, full_db, indirect_db", [(1, 30.5, 35.0), (2, 29.5, 33.5)])
def test_matches_the_path_tracer_with_the_same_bounces(cornell, bounces, full_db, indirect_db):
    layer, references = cornell
    relighter = open_cache_relighter(layer)
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
    layer, _ = cornell
    relighter = open_cache_relighter(layer)
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
    assert main(["bake", str(path), "--camera", cornell_box.CAMERA, "--out", str(out), "--width", "8",
                 "--height", "8", "--supersampling", "1"]) == 0
    relighter = open_cache_relighter(out / "cornell_box.relight.usda")
    assert isinstance(relighter, Relighter)


def test_cli_bakes_and_renders_a_quantised_transfer_cache(tmp_path):
    path = cornell_box.write(tmp_path)
    out = tmp_path / "cache"
    assert main(["bake", str(path), "--camera", cornell_box.CAMERA, "--out", str(out), "--width", "16",
                 "--height", "16", "--supersampling", "1", "--method", "transfer", "--gathers", "256",
                 "--coefficients", "30", "--quantize"]) == 0
    assert not list(out.glob(".cornell_box.transfer-*"))  # the resumable chunks are cleaned up
    assert (out / "cornell_box.finalGatherValues.npy").is_file()
    exr = tmp_path / "render.exr"
    assert main(["render", str(out / "cornell_box.relight.usda"), "-o", str(exr)]) == 0
    channels, _ = read_exr(exr)
    image = np.stack([channels[c] for c in ("R", "G", "B")], axis=-1)
    assert np.isfinite(image).all() and image.mean() > 0
    assert main(["bake", str(path), "--camera", cornell_box.CAMERA, "--out", str(out), "--method", "transfer",
                 "--gathers", "100"]) != 0
