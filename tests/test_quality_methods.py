"""`relight bake --quality PSNR` for the cuts and multiview methods: their ladders reach the target."""

from __future__ import annotations

from pipeline.benchmarks.rows import parse_params
from pipeline.cli import main
from pipeline.reference.path_tracer import PathTracer, ReferenceSettings
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES
from relight_torch.cache.layer import read_cache_layer
from relight_torch.cuts.open import open_cuts_relighter
from relight_torch.cuts.relighter import CutsRelightSettings
from relight_torch.metrics import psnr

TARGET_DB = 26.0


def test_cuts_sized_for_a_target_record_their_choice_and_meet_it(tmp_path):
    bundled = SCENES["dome"]
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
                "24",
                "--method",
                "cuts",
                "--out",
                str(tmp_path / "sized"),
                "--quality",
                str(TARGET_DB),
            ]
        )
        == 0
    )
    layer = tmp_path / "sized" / "dome.relight.usda"
    parameters = read_cache_layer(layer).parameters
    choice = parse_params(parameters["qualityChoice"])
    assert choice["mode"] == "env" and int(choice["lights"]) == parameters["cutsLights"]
    assert parameters["qualityMeasured"] >= TARGET_DB

    # An independent check: another seed, more spp, raw PSNR, at the chosen illumination cut size.
    scene = load_scene(shot, width=32, height=24)
    reference = (
        PathTracer(scene, ReferenceSettings(spp=256, max_bounces=0, seed=7))
        .render(find_camera(scene, bundled.camera))
        .mean
    )
    relighter = open_cuts_relighter(layer, cuts_settings=CutsRelightSettings(max_cut=int(choice["cut"])))
    assert psnr(relighter.render().numpy(), reference) >= TARGET_DB
