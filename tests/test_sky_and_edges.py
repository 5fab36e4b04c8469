"""Ordinary cases that real shots hit and bundled rooms never do: open sky (empty chunks of rows,
images that see no geometry at all), one-row images, and a camera inside closed geometry.

Every command (bake with each method, render, reference, info) runs on an exterior shot of
instanced teapots (`tests/sky_support.py`) through `pipeline.cli.main`, with texture samples 2,
at tiny sizes and small method settings. No light reaches the sky and there is no dome, so sky
pixels must stay black; inside the closed box no light reaches anything.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.bake.deep_framebuffer import bake_deep_framebuffer
from pipeline.cli import main
from pipeline.scene import find_camera, load_scene
from relight_torch.io.exr import read_exr
from sky_support import write_exterior_shot

# Small settings per method: each bakes in about a second at these sizes.
METHOD_OPTIONS = {
    "direct": [],
    "transfer": ["--gathers", "16", "--coefficients", "8"],
    "gather": ["--directions", "16", "--clusters", "4", "--representatives", "16"],
    "cuts": ["--mode", "indirect", "--cut-lights", "16"],
    # The 400 m floor makes the scene's bounds too flat for caching cameras: a box around the teapots.
    "multiview": ["--caching-resolution", "16", "--coverage", "0.5", "--box", "-3", "0", "-4", "4", "2", "4"],
}

# case -> (camera, width, height): sky everywhere, sky in the top half, at two resolutions each; one row;
# the inside of a closed box.
CASES = {
    "sky-16x12": ("Sky", 16, 12),
    "sky-8x6": ("Sky", 8, 6),
    "horizon-16x12": ("Horizon", 16, 12),
    "horizon-24x18": ("Horizon", 24, 18),
    "one-row": ("Horizon", 16, 1),
    "inside": ("Inside", 8, 6),
}


@pytest.fixture(scope="module")
def shot(tmp_path_factory):
    return write_exterior_shot(tmp_path_factory.mktemp("exterior"), teapots=4, sphere_lights=2)


def _rgb(path) -> np.ndarray:
    channels, _ = read_exr(path)
    return np.stack([channels[c] for c in "RGB"], -1)


def _check_image(image: np.ndarray, case: str) -> None:
    """Finite; black where only sky is seen (no dome) and everywhere inside the box; lit below the
    horizon."""
    assert np.isfinite(image).all()
    camera, _, height = CASES[case]
    if camera in ("Sky", "Inside"):
        assert not image.any(), f"{case}: light where there is only sky or a closed box"
    elif height > 1:
        assert not image[: height // 2 - 1].any(), f"{case}: light in the sky above the horizon"
        assert image[height // 2 + 1 :].sum() > 0, f"{case}: nothing lit below the horizon"


def test_texture_filtering_of_rows_that_see_only_sky(shot):
    """The issue's traceback: a chunk of rows with no hit and texture samples 2 (regression)."""
    scene = load_scene(shot, width=32, height=24)
    sky_rows = bake_deep_framebuffer(scene, find_camera(scene, "/Shot/Cams/Horizon"), 2, 2, rows=(0, 4))
    assert sky_rows.gbuffer.num_samples == 0
    everything = bake_deep_framebuffer(scene, find_camera(scene, "/Shot/Cams/Sky"), 2, 2)
    assert everything.gbuffer.num_samples == 0
    ground = bake_deep_framebuffer(scene, find_camera(scene, "/Shot/Cams/Horizon"), 2, 2, rows=(16, 24))
    assert ground.gbuffer.num_samples == 8 * 2 * 32 * 2


def test_bake_of_rows_that_see_only_sky(shot, tmp_path):
    """`relight bake` with texture samples 2 on a camera that sees only sky ends in a cache, not the
    issue's traceback."""
    assert (
        main(
            [
                "bake",
                str(shot),
                "--camera",
                "/Shot/Cams/Sky",
                "--width",
                "32",
                "--height",
                "24",
                "--texture-samples",
                "2",
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    assert (tmp_path / "exterior.relight.usda").is_file()


def _bake(shot, out, case: str, method: str) -> Path:
    camera, width, height = CASES[case]
    assert (
        main(
            [
                "bake",
                str(shot),
                "--camera",
                f"/Shot/Cams/{camera}",
                "--width",
                str(width),
                "--height",
                str(height),
                "--texture-samples",
                "2",
                "--method",
                method,
                "--out",
                str(out),
                *METHOD_OPTIONS[method],
            ]
        )
        == 0
    )
    return out / "exterior.relight.usda"


@pytest.mark.slow
@pytest.mark.parametrize("method", sorted(set(METHOD_OPTIONS) - {"multiview"}))
@pytest.mark.parametrize("case", sorted(CASES))
def test_bake_and_render(shot, tmp_path, case, method, capsys):
    _, width, height = CASES[case]
    layer = _bake(shot, tmp_path / "cache", case, method)
    image_path = tmp_path / "image.exr"
    assert main(["render", str(layer), "-o", str(image_path)]) == 0
    image = _rgb(image_path)
    assert image.shape == (height, width, 3)
    _check_image(image, case)
    assert main(["info", str(layer)]) == 0
    assert "Traceback" not in capsys.readouterr().err


@pytest.fixture(scope="module")
def multiview_cache(shot, tmp_path_factory):
    """One multiview cache of the level camera: its placement of caching cameras does not depend on
    the view and costs most of a bake (maximal empty spheres), so the other cases render from it."""
    return _bake(shot, tmp_path_factory.mktemp("multiview"), "horizon-16x12", "multiview")


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(CASES))
def test_multiview_render(multiview_cache, tmp_path, case):
    """A multiview cache renders every case's camera and size (the new-view path)."""
    camera, width, height = CASES[case]
    out = tmp_path / "image.exr"
    assert (
        main(
            [
                "render",
                str(multiview_cache),
                "--camera",
                f"/Shot/Cams/{camera}",
                "--width",
                str(width),
                "--height",
                str(height),
                "-o",
                str(out),
            ]
        )
        == 0
    )
    image = _rgb(out)
    assert image.shape == (height, width, 3)
    _check_image(image, case)


@pytest.mark.slow
def test_multiview_bake_of_only_sky(shot, tmp_path):
    layer = _bake(shot, tmp_path / "cache", "sky-8x6", "multiview")
    assert main(["render", str(layer), "-o", str(tmp_path / "image.exr")]) == 0
    _check_image(_rgb(tmp_path / "image.exr"), "sky-8x6")
    assert main(["info", str(layer)]) == 0


@pytest.mark.parametrize("case", sorted(CASES))
def test_reference(shot, tmp_path, case):
    camera, width, height = CASES[case]
    out = tmp_path / "reference.exr"
    assert (
        main(
            [
                "reference",
                str(shot),
                "--camera",
                f"/Shot/Cams/{camera}",
                "--width",
                str(width),
                "--height",
                str(height),
                "--spp",
                "1",
                "--max-bounces",
                "1",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    image = _rgb(out)
    assert image.shape == (height, width, 3)
    _check_image(image, case)
