"""Light shared by the sub-samples of a pixel on one surface (`relight_torch.direct.sharing`).

The groups split at silhouettes, creases and material changes; a filtered light traces one shadow
ray per group instead of per sub-sample; each sub-sample still takes its own material colours;
and the frame stays within a measured distance of the per-sub-sample one and of the truth.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from pxr import UsdGeom, UsdLux

from pipeline import cli
from pipeline.scenes import SCENES, authoring
from pipeline.scenes.meshes import plane, torus, uv_sphere
from relight_torch.direct.relighter import Relighter, open_relighter
from relight_torch.direct.settings import RelightSettings
from relight_torch.direct.sharing import PixelGroups, pixel_owners, take_rows
from relight_torch.gbuffer import GBuffer
from relight_torch.metrics import psnr
from relighter_support import matte_params

WIDTH, HEIGHT = 96, 72
RADIUS = 4  # sub-samples: the filter of a 640x480 frame at this size's scale


def _plane_gbuffer(normals: np.ndarray, objects: np.ndarray, heights: np.ndarray | None = None) -> GBuffer:
    """A (2, 4) sub-sample image (two pixels at s = 2) of points on the plane y = height, with the
    given (2, 4, 3) shading normals and (2, 4) object ids; every sub-sample covered."""
    rows, columns = np.mgrid[0:2, 0:4].astype(np.float32)
    heights = np.zeros((2, 4), np.float32) if heights is None else heights
    position = np.stack((columns * 0.01, heights, rows * 0.01), -1).reshape(-1, 3)
    n = position.shape[0]
    return GBuffer.from_numpy(
        (2, 4),
        np.arange(n),
        matte_params(n),
        np.array([0.0, 1.0, 0.0], np.float32),
        position=position,
        normal=normals.reshape(-1, 3).astype(np.float32),
        tangent=np.tile(np.float32([1, 0, 0]), (n, 1)),
        bitangent=np.tile(np.float32([0, 0, 1]), (n, 1)),
        geometric_normal=np.tile(np.float32([0, 1, 0]), (n, 1)),
        material_id=np.zeros(n, np.int32),
        object_id=objects.reshape(-1).astype(np.int32),
        depth=np.ones(n, np.float32),
    )


def test_groups_split_at_objects_creases_and_steps():
    up = np.tile(np.float32([0, 1, 0]), (2, 4, 1))
    # One surface: each pixel's four sub-samples share the top-left one's light.
    owner = pixel_owners(_plane_gbuffer(up, np.zeros((2, 4))), 2)
    assert owner.tolist() == [0, 0, 2, 2, 0, 0, 2, 2]
    # Another object in the right pixel's bottom row: those two form their own group.
    objects = np.zeros((2, 4))
    objects[1, 2:] = 1
    assert pixel_owners(_plane_gbuffer(up, objects), 2).tolist() == [0, 0, 2, 2, 0, 0, 6, 6]
    # A crease of 10 degrees and a step off the tangent plane keep a sub-sample apart.
    tilted = up.copy()
    tilted[0, 1] = (np.sin(np.radians(10.0)), np.cos(np.radians(10.0)), 0.0)
    heights = np.zeros((2, 4), np.float32)
    heights[1, 3] = 0.01
    owner = pixel_owners(_plane_gbuffer(tilted, np.zeros((2, 4)), heights), 2)
    assert owner.tolist() == [0, 1, 2, 2, 0, 0, 2, 7]


def test_owners_of_a_chunk_expand_to_its_points():
    up = np.tile(np.float32([0, 1, 0]), (2, 4, 1))
    groups = PixelGroups(_plane_gbuffer(up, np.zeros((2, 4))), 2)
    assert groups.owners.tolist() == [0, 2]
    # The groups' centroids: each pixel's four sub-samples, 0.005 in from its first.
    torch.testing.assert_close(groups.gbuffer.position, torch.tensor([[0.005, 0.0, 0.005], [0.025, 0.0, 0.005]]))
    for chunk in (slice(3, 7), torch.tensor([1, 4, 6])):
        rows, which = groups.of(chunk)
        owners = groups.owners[rows] if isinstance(rows, slice) else groups.owners.index_select(0, rows)
        points = torch.arange(8)[chunk]
        assert torch.equal(owners.index_select(0, which), groups.owner.index_select(0, points))
    values = torch.arange(2 * 3 * 5 * 2, dtype=torch.float32).reshape(2, 3, 5, 2)
    index = torch.tensor([4, 0, 0, 2])
    assert torch.equal(take_rows(values, 2, index), values.index_select(2, index))
    assert take_rows(values[:, :, :0], 2, index[:0]).shape == (2, 3, 0, 2)


@pytest.fixture(scope="module")
def cornell(tmp_path_factory) -> Relighter:
    root = tmp_path_factory.mktemp("sharing")
    shot = SCENES["cornell_box"].write(root / "scene")
    arguments = ["bake", str(shot), "--camera", SCENES["cornell_box"].camera, "--out", str(root / "cache")]
    arguments += ["--method", "direct", "--width", str(WIDTH), "--height", str(HEIGHT), "--supersampling", "2"]
    assert cli.main(arguments + ["--texture-samples", "1"]) == 0
    return open_relighter(next((root / "cache").glob("*.relight.usda")))


def _relighter(cornell: Relighter, gbuffer: GBuffer | None = None, **settings) -> Relighter:
    relighter = Relighter(
        cornell.gbuffer if gbuffer is None else gbuffer,
        cornell.visibility,
        cornell.supersampling,
        cornell.exposure_scale,
        RelightSettings(**settings),
    )
    relighter.set_lights(cornell.lights)
    return relighter


def test_a_filtered_light_traces_one_ray_per_group(cornell):
    rays = {}
    for shared in (True, False):
        relighter = _relighter(cornell, shadow_filter_radius=RADIUS, shared_lighting=shared)
        before = cornell.visibility.num_rays
        relighter.render()
        rays[shared] = cornell.visibility.num_rays - before
    groups = PixelGroups(cornell.gbuffer, cornell.supersampling)
    # Tiles of consecutive sub-samples share a pixel row at their seams: its owners are traced twice.
    assert 0 < rays[True] <= groups.owners.shape[0] + WIDTH < cornell.gbuffer.num_samples / 3
    assert rays[False] > 3 * rays[True]


def test_each_sub_sample_keeps_its_own_material(cornell):
    """Under an unshadowed light, a shared frame is the per-sub-sample frame of a G-buffer whose
    sub-samples stand at their groups' centroids with their owners' samples, each with its own
    colours."""
    g = cornell.gbuffer
    groups = PixelGroups(g, cornell.supersampling)
    # A colour per sub-sample, unlike its owner's: the shared light must not carry the owner's.
    stripes = torch.stack((torch.arange(g.num_samples) % 3 == 0,) * 3, -1).to(g.position.dtype)
    params = dataclasses.replace(g.params, diffuse_color=g.params.diffuse_color * (0.25 + stripes))
    coloured = dataclasses.replace(g, params=params)
    at_centroids = {
        name: getattr(groups.gbuffer, name).index_select(0, groups.rank)
        for name in ("position", "normal", "geometric_normal")
    }
    moved = dataclasses.replace(coloured, **at_centroids)
    unshadowed = [
        dataclasses.replace(light, shadow=dataclasses.replace(light.shadow, enable=False)) for light in cornell.lights
    ]
    shared = _relighter(cornell, coloured, shadow_filter_radius=RADIUS)
    separate = _relighter(cornell, moved, shadow_filter_radius=RADIUS, shared_lighting=False)
    samples = separate.fixed_samples(1)
    samples.copy_(samples.index_select(0, groups.owner))  # the owners' fixed samples, in the kept tensor
    for relighter in (shared, separate):
        relighter.set_lights(unshadowed)
    torch.testing.assert_close(shared.render_samples(), separate.render_samples(), rtol=1e-5, atol=1e-6)


def test_shared_frames_against_the_truth(cornell):
    # Measured against 256 unfiltered samples per sub-sample: one filtered sample per sub-sample
    # (four per pixel) 46.2 dB; shared, one per group (one per pixel) 44.2, two per group 46.1. The
    # shared light loses only the samples it does not take.
    truth = _relighter(cornell, area_samples=256, shadow_filter_radius=0, shared_lighting=False).render().numpy()
    separate = _relighter(cornell, shadow_filter_radius=RADIUS, shared_lighting=False).render().numpy()
    shared = _relighter(cornell, shadow_filter_radius=RADIUS).render().numpy()
    two = _relighter(cornell, shadow_filter_radius=RADIUS, filtered_area_samples=2).render().numpy()
    assert psnr(separate, truth) >= 45.7
    assert psnr(shared, truth) >= 43.7
    assert psnr(two, truth) >= 45.6


def _curved_matte_shot(path) -> str:
    """Large matte curved objects under a low side light: an implicit sphere, a coarse uv sphere
    (20 x 10 facets, smooth normals) and a torus on a floor, metres."""
    stage = authoring.create_stage(1.0, "curved matte objects")
    material, _ = authoring.define_preview_material(stage, "Matte", diffuseColor=(0.5, 0.5, 0.5), roughness=0.7)
    ball = UsdGeom.Sphere.Define(stage, "/World/Geometry/Ball")
    ball.CreateRadiusAttr(1.5)
    authoring.place(ball, (-1.6, 1.5, 0.0))
    facets = authoring.define_mesh(stage, "/World/Geometry/Facets", uv_sphere(1.2, 20, 10))
    authoring.place(facets, (1.8, 1.2, 0.5))
    ring = authoring.define_mesh(stage, "/World/Geometry/Ring", torus(0.9, 0.35, 24, 12))
    authoring.place(ring, (0.3, 0.35, 2.5))
    floor = authoring.define_mesh(stage, "/World/Geometry/Floor", plane(20.0, 20.0))
    for prim in (ball, facets, ring, floor):
        authoring.bind_material(prim.GetPrim(), material)
    light = UsdLux.SphereLight.Define(stage, "/World/Lights/Key")
    light.CreateRadiusAttr(0.3)
    authoring.set_light(light, intensity=40.0)
    authoring.place(light, (-6.0, 2.5, 4.0))
    authoring.define_camera(
        stage,
        "/World/Camera",
        (0.0, 3.0, 9.0),
        (0.0, 1.0, 0.0),
        focal_length_mm=35,
        aperture_mm=(36, 27),
        clipping_range=(0.1, 100.0),
    )
    return str(authoring.save_stage(stage, path))


@pytest.mark.parametrize("width, height", [(32, 24), (64, 48)])
def test_curved_matte_surfaces_do_not_shadow_themselves(tmp_path, width, height):
    """A group's centroid lies inside a convex surface; unlifted, a coarsely sampled sphere's groups
    shadowed themselves: the implicit sphere lost 10 % of its light at 32 x 24, the faceted one 11 %
    at 64 x 48, against their per-sub-sample frames. Lifted above its sub-samples' tangent planes,
    each object keeps its light within 1 %."""
    shot = _curved_matte_shot(tmp_path / "curved.usda")
    arguments = ["bake", shot, "--camera", "/World/Camera", "--out", str(tmp_path / "cache"), "--method", "direct"]
    arguments += ["--width", str(width), "--height", str(height), "--supersampling", "2", "--texture-samples", "1"]
    assert cli.main(arguments) == 0
    cache = open_relighter(next((tmp_path / "cache").glob("*.relight.usda")))
    shared = _relighter(cache, shadow_filter_radius=RADIUS).render_samples().sum(-1)
    separate = _relighter(cache, shadow_filter_radius=RADIUS, shared_lighting=False).render_samples().sum(-1)
    for index, path in enumerate(cache.object_paths):
        if path == "/World/Geometry/Floor":
            continue
        on = cache.gbuffer.object_id == index
        assert int(on.sum()) > 100, path
        assert float(shared[on].sum() / separate[on].sum()) == pytest.approx(1.0, abs=0.01), path
