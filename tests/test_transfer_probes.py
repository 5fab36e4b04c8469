"""The probe lights the transfer bake refits its F rows to (`pipeline.bake.transfer.probes`)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from pxr import UsdLux

from pipeline.bake.gather_cloud import create_gathers
from pipeline.bake.methods import bake_method
from pipeline.bake.transfer.probes import (
    MAX_OBJECT_PROBES,
    PROBES_PER_LIGHT,
    probe_budget,
    probe_lights,
    uniform_object_lights,
)
from pipeline.scene import find_camera, load_scene
from pipeline.scenes import SCENES, authoring, meshes
from pipeline.tracing import Tracer
from relight_torch.indirect_samples import GatherSamples
from relight_torch.transfer.haar import haar2d
from relight_torch.transfer.open import open_transfer_relighter
from relight_torch.transfer.responses import sparse_responses

# Nine floor tiles whose reflected power (area x albedo) falls by 1.5x from one to the next, their
# albedo alternating so that the area alone would rank them otherwise (0, 2, 1, ...), then eleven
# small grey tiles.
RANKED_TILES = [(math.sqrt(100.0 * 1.5 ** (8 - i) / albedo), albedo) for i, albedo in enumerate([0.3, 0.9] * 4 + [0.3])]
TILES = RANKED_TILES + [(8.0, 0.5)] * 11


def _tiled_floor(directory: Path) -> Path:
    """20 square tiles on a 5 x 4 grid (pitch 100 scene units), one object and material each,
    under one sphere light."""
    stage = authoring.create_stage(0.01, "tiles of decreasing reflected power")
    for index, (side, albedo) in enumerate(TILES):
        tile = authoring.define_mesh(stage, f"{authoring.GEOMETRY}/Tile{index:02d}", meshes.plane(side, side))
        authoring.place(tile, (100.0 * (index % 5), 0.0, 100.0 * (index // 5)))
        material, _ = authoring.define_preview_material(stage, f"Tile{index:02d}", diffuseColor=(albedo,) * 3)
        authoring.bind_material(tile.GetPrim(), material)
    lamp = UsdLux.SphereLight.Define(stage, f"{authoring.LIGHTS}/Lamp")
    lamp.CreateRadiusAttr(5.0)
    authoring.set_light(lamp.LightAPI(), intensity=1000.0)
    authoring.place(lamp, (200.0, 150.0, 150.0))
    return authoring.save_stage(stage, directory / "tiles.usda")


@pytest.fixture(scope="module")
def tiles(tmp_path_factory):
    scene = load_scene(_tiled_floor(tmp_path_factory.mktemp("tiles")))
    return scene, create_gathers(scene, 1024, seed=0), Tracer.for_scene(scene)


def _wavelet(radiance: torch.Tensor) -> torch.Tensor:
    """(G, 3) radiance -> (G,) the Haar coefficients of its channel sum (one bounce: no M)."""
    side = math.isqrt(radiance.shape[0])
    return haar2d(radiance.sum(-1).reshape(side, side, 1)).reshape(-1)


def test_probe_budget_is_a_quarter_of_the_kept_coefficients_in_whole_lights():
    assert [probe_budget(k) for k in (1, 12, 24, 50, 100, 400)] == [3, 3, 6, 12, 24, 99]


def test_uniform_object_lights_rank_objects_by_reflected_light_and_stop_at_the_cap():
    # 8 x 8 gathers over 10 objects of random area and albedo, object 3 black.
    generator = torch.Generator().manual_seed(0)
    num = 64
    object_id = torch.arange(num) % 10
    albedo = torch.rand(10, 3, generator=generator)[object_id]
    albedo[object_id == 3] = 0.0
    area = torch.rand(num, generator=generator) + 0.1
    zeros = torch.zeros(num, 3)
    gathers = GatherSamples(zeros, zeros, albedo, zeros, area, object_id)
    power = torch.zeros(10).index_add_(0, object_id, area * albedo.mean(-1))
    ranked = torch.argsort(power, descending=True).tolist()
    assert ranked[-1] == 3
    whole = albedo / math.pi

    four = uniform_object_lights(gathers, 4)
    assert len(four) == 4 and torch.equal(four[0], whole)
    for light, index in zip(four[1:], ranked[:3], strict=True):
        assert torch.equal(light, whole * (object_id == index).unsqueeze(-1))
    # Without a cap: the whole scene and every reflecting object but the weakest, which is what
    # the whole scene holds beyond the others; the black object nowhere.
    every = uniform_object_lights(gathers, 100)
    assert len(every) == 9
    weakest = every[0] - torch.stack(every[1:]).sum(0)
    assert torch.allclose(weakest, whole * (object_id == ranked[-2]).unsqueeze(-1))
    assert uniform_object_lights(gathers, 0) == []
    unknown = GatherSamples(zeros, zeros, albedo, zeros, area)
    assert len(uniform_object_lights(unknown, 4)) == 1


def test_probes_of_a_scene_with_many_objects_keep_the_shot_then_its_largest_objects(tiles):
    scene, gathers, tracer = tiles
    probes = probe_lights(scene, gathers, tracer, None, 1, 50, seed=0)
    # Within the budget of 50 coefficients (12): the lamp's three channels, the whole floor lit
    # uniformly and its three tiles that reflect most of such light.
    assert probes.shape == (PROBES_PER_LIGHT + MAX_OBJECT_PROBES, gathers.num_gathers) == (7, 1024)
    assert float(probes[:PROBES_PER_LIGHT].abs().sum()) > 0
    reflected = gathers.albedo / math.pi
    assert torch.allclose(probes[PROBES_PER_LIGHT], _wavelet(reflected), rtol=1e-5, atol=1e-7)
    paths = [obj.path for obj in scene.objects]
    for row, tile in zip(probes[PROBES_PER_LIGHT + 1 :], range(MAX_OBJECT_PROBES - 1), strict=True):
        mine = gathers.object_id == paths.index(f"{authoring.GEOMETRY}/Tile{tile:02d}")
        assert torch.allclose(row, _wavelet(reflected * mine.unsqueeze(-1)), rtol=1e-5, atol=1e-7)


def test_a_smaller_budgets_probes_are_the_first_of_a_larger_one(tiles):
    # The pilot's culled variants refit to the first probe_budget(k) probes of the bake that kept
    # the most coefficients, as a bake at k would have made them.
    scene, gathers, tracer = tiles
    large = probe_lights(scene, gathers, tracer, None, 1, 400, seed=0)
    assert large.shape[0] == PROBES_PER_LIGHT + MAX_OBJECT_PROBES
    for num_kept in (12, 24, 50):
        small = probe_lights(scene, gathers, tracer, None, 1, num_kept, seed=0)
        assert torch.equal(small, large[: probe_budget(num_kept)])


def test_culled_variants_refit_to_the_probes_a_bake_at_their_count_keeps(tmp_path):
    # The pilot bakes the most coefficients once and culls; a 4-coefficient variant was refitted
    # to all 7 probes of the 100-coefficient bake (least squares: more constraints than values),
    # which bent even the lamp's light. It now keeps the 3 a bake at 4 would: the lamp's, exactly.
    bundled = SCENES["cornell_box"]
    scene = load_scene(bundled.write(tmp_path), width=16, height=16)
    adapter = bake_method("transfer").adapter
    point = {"gathers": 256, "coefficients": (4, 100), "bounces": 1}
    layer = adapter.bake(scene, find_camera(scene, bundled.camera), tmp_path, "cb", point, 1, 1)
    probes = torch.from_numpy(np.load(tmp_path / "cb.transferProbes.npy"))
    assert probe_budget(4) == PROBES_PER_LIGHT < 4 < probes.shape[0] <= probe_budget(100)
    baked = open_transfer_relighter(layer).final_gather
    culled = adapter.variants(layer, point, "cpu")[0].relighter.final_gather
    lamp = probes[:PROBES_PER_LIGHT]
    exact = sparse_responses(baked, lamp)
    error = (sparse_responses(culled, lamp) - exact).abs().max() / exact.abs().max()
    assert float(error) < 2e-3  # float16 values
