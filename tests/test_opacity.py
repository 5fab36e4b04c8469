"""The shared opacity lookup (`relight_torch.visibility.opacity`) and the ray casters and shadow
maps that use it: cut-out holes let rays through, partial opacity is stochastic presence."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import stats

from relight_torch.lights.light import Light, LightKind
from relight_torch.visibility.embree import MAX_TRANSPARENT_LAYERS, EmbreeCaster, ShadowLinkCasters
from relight_torch.visibility.opacity import OpacityMap, OpacityTable, cut_out, presence_random
from relight_torch.visibility.rays import RayVisibility
from relight_torch.visibility.shadow_maps import ShadowMapVisibility


def quad(z: float, low=(0.0, 0.0), high=(1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles of the axis-aligned square [low, high] at height z, facing +z, and their
    corner uvs: u runs along +x and v along +y, (0, 0) at `low`."""
    (x0, y0), (x1, y1) = low, high
    corners = np.array([[(x0, y0, z), (x1, y0, z), (x1, y1, z)], [(x0, y0, z), (x1, y1, z), (x0, y1, z)]], np.float32)
    uvs = np.array([[(0, 0), (1, 0), (1, 1)], [(0, 0), (1, 1), (0, 1)]], np.float32)
    return corners, uvs


def half_texture(hole: str) -> torch.Tensor:
    """(4, 4) opacity texels (row 0 the top), 0 on one half ('left' or 'top'), 1 on the other."""
    texels = torch.ones(4, 4)
    if hole == "left":
        texels[:, :2] = 0.0
    else:
        texels[:2, :] = 0.0
    return texels


def table(uvs: np.ndarray, triangles: list[int], opacity_map: OpacityMap) -> OpacityTable:
    return OpacityTable(
        torch.tensor(triangles, dtype=torch.int64),
        torch.zeros(len(triangles), dtype=torch.int64),
        torch.from_numpy(uvs),
        (opacity_map,),
    )


def screen_over_floor(opacity_map: OpacityMap) -> tuple[np.ndarray, OpacityTable]:
    """A unit screen at z = 1 (triangles 0, 1, with `opacity_map`) over an opaque floor at z = 0 (2, 3)."""
    screen, uvs = quad(1.0)
    floor, _floor_uvs = quad(0.0, (-4.0, -4.0), (4.0, 4.0))
    return np.concatenate([screen, floor]), table(uvs, [0, 1], opacity_map)


def down_rays(x: np.ndarray, y: np.ndarray, z: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    origins = np.stack([x, y, np.full_like(x, z)], -1).astype(np.float32)
    return origins, np.broadcast_to(np.float32([0, 0, -1]), origins.shape).copy()


def test_cut_out_thresholds_numpy_and_torch():
    values = np.array([-0.5, 0.2, 0.5, 0.7, 1.5], np.float32)
    np.testing.assert_allclose(cut_out(values, 0.0), [0.0, 0.2, 0.5, 0.7, 1.0])
    np.testing.assert_array_equal(cut_out(values, 0.5), [0, 0, 1, 1, 1])
    assert torch.equal(cut_out(torch.from_numpy(values), 0.6), torch.tensor([0.0, 0, 0, 1, 1]))


def test_presence_random_is_uniform_and_deterministic():
    keys = torch.stack([torch.arange(200_000), torch.full((200_000,), 7)], -1)
    values = presence_random(keys)
    assert values.min() >= 0 and values.max() < 1
    assert stats.kstest(values.numpy(), "uniform").pvalue > 1e-3
    # The same key decides the same way in any batch.
    assert torch.equal(presence_random(keys[1000:1010]), values[1000:1010])
    # Neighbouring keys are uncorrelated.
    assert abs(np.corrcoef(values[:-1].numpy(), values[1:].numpy())[0, 1]) < 0.01


def test_lookup_hand_values_and_orientation():
    """Texel centres give the texels; st (0, 0) is the image's lower-left (bilinear between texel
    centres 1 and 2 of a row is 0.5 half-way)."""
    _, uvs = quad(0.0)
    left = table(uvs, [0, 1], OpacityMap(1.0, texels=half_texture("left"), wrap_s="clamp", wrap_t="clamp"))
    # Triangle 0 has uv = u1 * (1, 0) + u2 * (1, 1) + (1 - u1 - u2) * (0, 0):
    # barycentrics (u1, u2) give uv (u1 + u2, u2).
    barycentrics = torch.tensor([[0.125 - 0.1, 0.1], [0.875 - 0.1, 0.1], [0.5 - 0.1, 0.1]])
    np.testing.assert_allclose(left.opacity(torch.zeros(3, dtype=torch.long), barycentrics), [0.0, 1.0, 0.5])
    top = table(uvs, [0, 1], OpacityMap(1.0, texels=half_texture("top"), wrap_s="clamp", wrap_t="clamp", threshold=0.5))
    # Triangle 1: uv = u1 * (1, 1) + u2 * (0, 1): high v is the top of the image (the hole).
    barycentrics = torch.tensor([[0.1, 0.8], [0.1, 0.05]])
    np.testing.assert_array_equal(top.opacity(torch.ones(2, dtype=torch.long), barycentrics), [0.0, 1.0])
    # A triangle the table does not list, and a miss, are opaque.
    np.testing.assert_array_equal(top.opacity(torch.tensor([5, -1]), torch.zeros(2, 2)), [1.0, 1.0])


def test_table_arrays_round_trip_and_subset():
    _, uvs = quad(0.0)
    st = torch.tensor([[2.0, 0.0, 0.25], [0.0, 1.0, 0.0]], dtype=torch.float64)
    original = OpacityTable(
        torch.tensor([3, 8]),
        torch.tensor([1, 0]),
        torch.from_numpy(uvs),
        (
            OpacityMap(0.4, mode="presence"),
            OpacityMap(1.0, 0.5, "transparent", half_texture("left"), "mirror", "black", 0.9, 0.05, st),
        ),
    )
    restored = OpacityTable.from_arrays(original.to_arrays())
    triangles = torch.tensor([3, 3, 8, 8, 4])
    barycentrics = torch.rand(5, 2, generator=torch.Generator().manual_seed(1)) * 0.5
    assert torch.equal(restored.opacity(triangles, barycentrics), original.opacity(triangles, barycentrics))
    assert restored.maps[1].wrap_s == "mirror" and restored.maps[0].mode == "presence"
    keep = np.zeros(10, bool)
    keep[[1, 8, 9]] = True
    subset = original.subset(keep)
    assert subset.triangles.tolist() == [1] and subset.map_index.tolist() == [0]
    with pytest.raises(ValueError, match="opacityMaps"):
        OpacityTable.from_arrays({**original.to_arrays(), "opacityMaps": np.zeros((2, 3))})


@pytest.mark.parametrize("hole", ["left", "top"])
def test_rays_pass_through_cut_out_holes(hole):
    corners, opacity = screen_over_floor(
        OpacityMap(1.0, 0.5, texels=half_texture(hole), wrap_s="clamp", wrap_t="clamp")
    )
    caster = EmbreeCaster(corners, opacity=opacity)
    grid = (np.arange(16) + 0.5) / 16
    x, y = (a.ravel() for a in np.meshgrid(grid, grid))
    origins, directions = down_rays(x, y)
    in_hole = x < 0.5 if hole == "left" else y > 0.5
    hits = caster.intersect(origins, directions)
    np.testing.assert_allclose(hits.distance, np.where(in_hole, 2.0, 1.0), atol=1e-5)
    assert np.all(hits.triangle_id[in_hole] >= 2) and np.all(hits.triangle_id[~in_hole] < 2)
    # Shadow rays from the floor up to z = 1.5: blocked by the screen outside its hole only.
    up_origins = np.stack([x, y, np.full_like(x, 1e-3)], -1).astype(np.float32)
    blocked = caster.occluded(up_origins, -directions, np.full(x.size, 1.5, np.float32))
    np.testing.assert_array_equal(blocked, ~in_hole)
    # Without the table the screen is solid.
    assert np.all(EmbreeCaster(corners).occluded(up_origins, -directions, np.full(x.size, 1.5, np.float32)))


def test_partial_opacity_is_stochastic_presence():
    """Three stacked screens of opacity 0.4: a ray gets through with probability 0.6^3, and stops
    at screen k with probability 0.4 x 0.6^k."""
    opacity_map = OpacityMap(0.4)
    layers = [quad(z) for z in (1.0, 1.5, 2.0)]
    corners = np.concatenate([c for c, _ in layers])
    uvs = np.concatenate([u for _, u in layers])
    caster = EmbreeCaster(corners, opacity=table(uvs, list(range(6)), opacity_map))
    rng = np.random.default_rng(3)
    num_rays = 20_000
    x, y = rng.random(num_rays), rng.random(num_rays)
    origins, directions = down_rays(x, y, 3.0)
    hits = caster.intersect(origins, directions)
    counts = [np.count_nonzero(np.isclose(hits.distance, d, atol=1e-4)) for d in (1.0, 1.5, 2.0)]
    expected = [0.4, 0.4 * 0.6, 0.4 * 0.36]
    for count, p in zip(counts + [np.count_nonzero(~hits.hit)], expected + [0.6**3], strict=True):
        assert abs(count - p * num_rays) < 5 * np.sqrt(num_rays * p * (1 - p)), (counts, p)
    blocked = caster.occluded(origins, directions, np.full(num_rays, 10.0, np.float32))
    assert abs(blocked.mean() - (1 - 0.6**3)) < 5 * np.sqrt(0.216 * 0.784 / num_rays)
    # Deterministic: the same rays decide the same way.
    np.testing.assert_array_equal(caster.occluded(origins, directions, np.full(num_rays, 10.0, np.float32)), blocked)


def test_pass_through_loop_is_bounded():
    """More fully transparent layers than MAX_TRANSPARENT_LAYERS: the ray stops at the last one
    it may pass (documented), instead of looping on."""
    num_layers = MAX_TRANSPARENT_LAYERS + 6
    layers = [quad(float(k + 1)) for k in range(num_layers)]
    corners = np.concatenate([c for c, _ in layers])
    uvs = np.concatenate([u for _, u in layers])
    caster = EmbreeCaster(corners, opacity=table(uvs, list(range(2 * num_layers)), OpacityMap(0.0)))
    origins, directions = down_rays(np.array([0.3]), np.array([0.6]), num_layers + 1.0)
    hits = caster.intersect(origins, directions)
    assert hits.hit[0] and hits.distance[0] == pytest.approx(float(MAX_TRANSPARENT_LAYERS), abs=1e-3)


def test_shadow_link_casters_keep_the_holes():
    corners, opacity = screen_over_floor(
        OpacityMap(1.0, 0.5, texels=half_texture("left"), wrap_s="clamp", wrap_t="clamp")
    )
    links = ShadowLinkCasters(corners, np.array([0, 0, 1, 1]), ["/Screen", "/Floor"], 1e-4, opacity=opacity)
    caster = links(("/Screen",))
    origins = np.float32([[0.25, 0.5, 0.5], [0.75, 0.5, 0.5]])
    blocked = caster.occluded(origins, np.float32([[0, 0, 1], [0, 0, 1]]), np.float32([2.0, 2.0]))
    np.testing.assert_array_equal(blocked, [False, True])


def test_shadow_maps_agree_with_embree_through_holes():
    """A point light above a lattice-like screen: shadow-map and Embree visibility of floor points
    agree except within a texel of the holes' edges."""
    texels = torch.zeros(8, 8)
    texels[::2, :] = 1.0  # horizontal bars: every other texel row
    corners, opacity = screen_over_floor(OpacityMap(1.0, 0.5, texels=texels, wrap_s="clamp", wrap_t="clamp"))
    light = Light(
        path="/Light",
        kind=LightKind.SPHERE,
        radius=0.0,
        world_from_light=np.array([[1, 0, 0, 0.5], [0, 1, 0, 0.5], [0, 0, 1, 3.0], [0, 0, 0, 1]], float),
    )
    grid = (np.arange(64) + 0.5) / 64 * 1.6 - 0.2963  # no point exactly on a bar edge's shadow
    x, y = (a.ravel() for a in np.meshgrid(grid, grid))
    points = torch.from_numpy(np.stack([x, y, np.zeros_like(x)], -1)).float()
    normals = torch.tensor([0.0, 0.0, 1.0]).expand_as(points)
    to_light = torch.tensor([0.5, 0.5, 3.0]) - points
    distances = to_light.norm(dim=-1, keepdim=True)
    directions = (to_light / distances).unsqueeze(1)
    rays = RayVisibility(EmbreeCaster(corners, opacity=opacity))
    exact = torch.isfinite(rays.occluder_distance(light, points, normals, directions, distances))
    maps = ShadowMapVisibility(torch.from_numpy(corners), resolution=512, opacity=opacity)
    mapped = torch.isfinite(maps.occluder_distance(light, points, normals, directions, distances))
    solid = ShadowMapVisibility(torch.from_numpy(corners), resolution=512)
    assert 0.3 < exact.float().mean() < 0.6  # the bars shadow about half the screen's footprint
    assert (mapped != exact).float().mean() < 0.02
    assert (
        torch.isfinite(solid.occluder_distance(light, points, normals, directions, distances)) != exact
    ).float().mean() > 0.15
