"""Kernels of the direct-to-indirect transfer method, each against a slow twin or a hand value."""

from __future__ import annotations

import dataclasses
import math
import tracemalloc

import numpy as np
import pytest
import torch

from pipeline.bake.gather_cloud import flatten_order, refine_triangles, split_budget, triangle_areas
from pipeline.bake.transfer.rows import disc_points, disc_support, gather_transport
from relight_torch.indirect_samples import GatherSamples, gather_radiance
from relight_torch.lights.light import Light, LightKind
from relight_torch.transfer.encoding import EncodedRows, decode, decode_rows, encode, encode_rows
from relight_torch.transfer.haar import haar2d, inverse_haar2d, support_area
from relight_torch.transfer.sparse import SparseRows, concatenate, cull, factor_colour, keep_top_k
from relight_torch.visibility.embree import EmbreeCaster
from relight_torch.visibility.rays import RayVisibility


def paper_haar(image: np.ndarray) -> np.ndarray:
    """Listing 9-4 as printed, one (n, n, C) image, each level reading the previous level's output."""
    a = image.copy()
    side = a.shape[0]
    while side >= 2:
        b = a.copy()
        for i in range(0, side, 2):
            for j in range(0, side, 2):
                h = side // 2
                b[i // 2, j // 2] = 0.5 * (a[i, j] + a[i + 1, j] + a[i, j + 1] + a[i + 1, j + 1])
                b[i // 2, j // 2 + h] = 0.5 * (a[i, j] - a[i + 1, j] + a[i, j + 1] - a[i + 1, j + 1])
                b[i // 2 + h, j // 2] = 0.5 * (a[i, j] + a[i + 1, j] - a[i, j + 1] - a[i + 1, j + 1])
                b[i // 2 + h, j // 2 + h] = 0.5 * (a[i, j] - a[i + 1, j] - a[i, j + 1] + a[i + 1, j + 1])
        a = b
        side //= 2
    return a


def test_haar_matches_the_papers_loop(device):
    images = torch.rand((2, 8, 8, 3), generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    fast = haar2d(images.to(device)).cpu()
    for image, coefficients in zip(images.numpy(), fast.numpy(), strict=True):
        np.testing.assert_allclose(coefficients, paper_haar(image), rtol=1e-12, atol=1e-14)


def test_haar_is_orthonormal_and_inverts(device):
    images = torch.rand((3, 16, 16, 2), generator=torch.Generator().manual_seed(2), dtype=torch.float64).to(device)
    coefficients = haar2d(images)
    torch.testing.assert_close(inverse_haar2d(coefficients), images, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(coefficients.square().sum(), images.square().sum(), rtol=1e-12, atol=0)
    # The box coefficient of an n x n image is n times its mean.
    torch.testing.assert_close(coefficients[:, 0, 0], 16 * images.mean(dim=(1, 2)), rtol=1e-12, atol=1e-12)


def test_haar_rejects_non_power_of_two():
    with pytest.raises(ValueError, match="power of two"):
        haar2d(torch.zeros(6, 6, 1))


def test_support_area_by_hand():
    area = support_area(8)
    assert area[0, 0] == 64 and area[0, 1] == 64 and area[1, 1] == 64
    assert area[2, 3] == 16 and area[3, 0] == 16
    assert area[4, 7] == 4 and area[7, 7] == 4
    # Each level's basis functions tile the image: 3 kinds x (n / width)^2 functions x support.
    assert int(area.sum()) == 64 + 3 * 64 * 3


def _slow_top_k(coefficients: np.ndarray, k: int) -> list[set[int]]:
    side = coefficients.shape[1]
    area = np.array(
        [
            [(side * side if max(i, j) == 0 else (side // 2 ** int(math.log2(max(i, j)))) ** 2) for j in range(side)]
            for i in range(side)
        ]
    ).reshape(-1)
    kept = []
    for row in coefficients.reshape(coefficients.shape[0], side * side, -1):
        importance = np.abs(row).sum(-1) * area
        kept.append({int(i) for i in np.argsort(-importance, kind="stable")[:k] if np.any(row[i] != 0)})
    return kept


def test_top_k_keeps_the_area_weighted_largest():
    coefficients = torch.randn((5, 8, 8, 3), generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    coefficients[2] = 0.0
    coefficients[3, 1:] = 0.0  # a row with fewer than k non-zero values
    rows = keep_top_k(coefficients, 10)
    rows.check()
    expected = _slow_top_k(coefficients.numpy(), 10)
    for r in range(5):
        entries = slice(int(rows.offsets[r]), int(rows.offsets[r + 1]))
        assert set(rows.indices[entries].tolist()) == expected[r]
        flat = coefficients[r].reshape(64, 3)
        torch.testing.assert_close(rows.values[entries], flat[rows.indices[entries].long()])
    assert int(rows.offsets[3] - rows.offsets[2]) == 0


def test_top_k_prefers_wide_support_over_magnitude():
    coefficients = torch.zeros(1, 4, 4, 1)
    coefficients[0, 0, 1] = 0.1  # coarsest detail: 16 pixels, importance 1.6
    coefficients[0, 2, 3] = 0.3  # finest detail: 4 pixels, importance 1.2
    rows = keep_top_k(coefficients, 1)
    assert rows.indices.tolist() == [1]


def test_sparse_product_matches_dense(device):
    generator = torch.Generator().manual_seed(4)
    dense = torch.randn((6, 16, 16, 3), generator=generator, dtype=torch.float64)
    rows = concatenate([keep_top_k(dense[:4], 20), keep_top_k(dense[4:], 7)])
    rows.check()
    matrix = torch.zeros(6, 256, 3, dtype=torch.float64)
    row_of = torch.repeat_interleave(torch.arange(6), rows.offsets.diff())
    matrix[row_of, rows.indices.long()] = rows.values
    vector = torch.randn((256, 3), generator=generator, dtype=torch.float64)
    expected = torch.einsum("rgc,gc->rc", matrix, vector)
    product = rows.to(device, torch.float64).matmul(vector.to(device))
    torch.testing.assert_close(product.cpu(), expected, rtol=1e-12, atol=1e-12)


def _dense_matrix(rows: SparseRows) -> torch.Tensor:
    """(R, D, 3) dense twin of `rows` (row colour applied)."""
    matrix = torch.zeros(rows.num_rows, rows.num_columns, 3, dtype=rows.values.dtype)
    row_of = torch.repeat_interleave(torch.arange(rows.num_rows), rows.offsets.diff())
    matrix[row_of, rows.indices.long()] = rows.values
    return matrix if rows.row_colour is None else matrix * rows.row_colour[:, None, :]


def test_colour_factored_product_matches_dense(device):
    generator = torch.Generator().manual_seed(7)
    scalars = torch.randn((5, 8, 8, 1), generator=generator, dtype=torch.float64)
    colour = torch.rand((5, 3), generator=generator, dtype=torch.float64)
    rows = concatenate(
        [
            dataclasses.replace(keep_top_k(scalars[:2], 9), row_colour=colour[:2]),
            dataclasses.replace(keep_top_k(scalars[2:], 30), row_colour=colour[2:]),
        ]
    )
    rows.check()
    vector = torch.randn((64, 3), generator=generator, dtype=torch.float64)
    expected = torch.einsum("rgc,gc->rc", _dense_matrix(rows), vector)
    product = rows.to(device, torch.float64).matmul(vector.to(device))
    torch.testing.assert_close(product.cpu(), expected, rtol=1e-12, atol=1e-12)


def test_concatenate_refuses_rows_with_and_without_colour():
    # A first part without a colour used to drop the later parts' colours silently.
    scalars = torch.randn((4, 4, 4, 1), generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    coloured = dataclasses.replace(keep_top_k(scalars[2:], 5), row_colour=torch.rand(2, 3, dtype=torch.float64))
    for parts in ([keep_top_k(scalars[:2], 5), coloured], [coloured, keep_top_k(scalars[:2], 5)]):
        with pytest.raises(ValueError, match="row colour"):
            concatenate(parts)


def test_factor_colour_is_exact_for_one_colour_and_optimal_otherwise():
    generator = torch.Generator().manual_seed(8)
    shape = torch.randn((1, 4, 4, 1), generator=generator, dtype=torch.float64)
    albedo = torch.tensor([0.7, 0.2, 0.1], dtype=torch.float64)
    scalars, colour = factor_colour(shape * albedo)
    torch.testing.assert_close(scalars * colour[:, None, None, :], shape * albedo, rtol=1e-12, atol=1e-12)
    assert bool((colour > 0).all())
    # A mixed row: the residual is the best rank-1 residual (the SVD's trailing singular values).
    mixed = torch.randn((3, 4, 4, 3), generator=generator, dtype=torch.float64)
    scalars, colour = factor_colour(mixed)
    residual = (mixed - scalars * colour[:, None, None, :]).square().sum(dim=(1, 2, 3))
    singular = torch.linalg.svdvals(mixed.reshape(3, 16, 3))
    torch.testing.assert_close(residual, singular[:, 1:].square().sum(-1), rtol=1e-9, atol=1e-12)


def test_cull_equals_keeping_fewer_coefficients():
    coefficients = torch.randn((6, 16, 16, 3), generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    coefficients[4, 2:] = 0.0  # a row with fewer than k non-zero values
    culled = cull(keep_top_k(coefficients, 40), 12)
    culled.check()
    direct = keep_top_k(coefficients, 12)
    torch.testing.assert_close(culled.offsets, direct.offsets, rtol=0, atol=0)
    torch.testing.assert_close(culled.indices, direct.indices, rtol=0, atol=0)
    torch.testing.assert_close(culled.values, direct.values, rtol=0, atol=0)


@pytest.mark.parametrize("num_columns, index_dtype", [(1 << 16, np.uint16), (1 << 18, np.int32)])
def test_stored_indices_are_narrow_where_they_fit(num_columns, index_dtype):
    indices = torch.tensor([0, num_columns - 1, 5], dtype=torch.int32)
    rows = SparseRows(torch.rand(3, 1), indices, torch.tensor([0, 2, 3]), num_columns, torch.rand(2, 3))
    arrays = encode_rows(rows, "uint8").arrays()
    assert arrays["Indices"].dtype == index_dtype and arrays["Colour"].shape == (2, 3)
    back = decode_rows(EncodedRows.from_arrays(arrays, num_columns))
    back.check()
    assert back.indices.dtype == torch.int32 and back.indices.tolist() == indices.tolist()
    torch.testing.assert_close(back.row_colour, rows.row_colour)
    torch.testing.assert_close(back.values, rows.values, rtol=0, atol=0.5 / 255)


def test_sparse_check_names_broken_invariants():
    values = torch.ones(3, 3)
    with pytest.raises(ValueError, match="strictly increasing"):
        SparseRows(values, torch.tensor([2, 1, 0], dtype=torch.int32), torch.tensor([0, 3]), 4).check()
    with pytest.raises(ValueError, match=r"\[0, 4\)"):
        SparseRows(values, torch.tensor([0, 1, 4], dtype=torch.int32), torch.tensor([0, 3]), 4).check()
    with pytest.raises(ValueError, match="from 0 to nnz"):
        SparseRows(values, torch.tensor([0, 1, 2], dtype=torch.int32), torch.tensor([0, 2]), 4).check()


@pytest.mark.parametrize("encoding, relative_error", [("float16", 2.0**-11), ("uint8", 0.5 / 255)])
def test_encoding_error_is_bounded_per_row(encoding, relative_error):
    generator = torch.Generator().manual_seed(5)
    offsets = torch.tensor([0, 40, 40, 100])
    values = torch.randn((100, 3), generator=generator) * torch.tensor([1.0, 1e-6, 1e4])
    values[40:] *= 1e-3
    encoded = encode(values, offsets, encoding)
    decoded = decode(encoded, offsets)
    for start, stop in ((0, 40), (40, 100)):
        span = values[start:stop]
        scale = span.abs().amax(0) if encoding == "float16" else span.amax(0) - span.amin(0)
        assert bool(((decoded[start:stop] - span).abs() <= relative_error * scale * 1.0001).all())


def test_split_budget_divides_by_area():
    # Two far-apart groups of triangles with areas 1 and 3: a budget of 4 goes 1 and 3. The 3
    # split int(3 * 1.5 / 3) = 1 and 2 over the right pair; a one-triangle group shares its area.
    centroids = np.array([[0.0, 0, 0], [0.1, 0, 0], [10.0, 0, 0], [10.1, 0, 0]])
    areas = np.array([0.5, 0.5, 1.5, 1.5])
    triangle, area = split_budget(centroids, areas, 4, np.random.default_rng(0))
    assert np.count_nonzero(triangle < 2) == 1
    np.testing.assert_allclose(area.sum(), areas.sum())
    np.testing.assert_allclose(np.sort(area), [0.75, 0.75, 1.0, 1.5])


def test_split_budget_holds_a_few_bytes_per_triangle_beyond_its_inputs():
    """A production set's tens of millions of triangles: the split's temporaries were 88 bytes a
    triangle over its inputs (three float64 (T, 3) copies, int64 orders), 3 GB at 33.6 M."""
    num_triangles = 200_000
    rng = np.random.default_rng(0)
    centroids = rng.random((num_triangles, 3))
    areas = rng.random(num_triangles)
    tracemalloc.start()
    try:
        triangle, area = split_budget(centroids, areas, 4096, np.random.default_rng(1))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak / num_triangles < 40
    assert np.unique(triangle).shape[0] == 4096
    np.testing.assert_allclose(area.sum(), areas.sum())


def test_refine_keeps_area_and_winding():
    corners = np.array([[[0.0, 0, 0], [4.0, 0, 0], [0.0, 1, 0]]])
    uvs = np.array([[[0.0, 0], [1.0, 0], [0.0, 1]]])
    refined, refined_uvs, parent = refine_triangles(corners, uvs, 0.3)
    assert triangle_areas(refined).max() <= 0.3
    np.testing.assert_allclose(triangle_areas(refined).sum(), 2.0)
    normals = np.cross(refined[:, 1] - refined[:, 0], refined[:, 2] - refined[:, 0])
    assert (normals[:, 2] > 0).all() and (parent == 0).all()
    # uvs follow the positions linearly (here uv = (x / 4, y)).
    np.testing.assert_allclose(refined_uvs, np.stack([refined[..., 0] / 4, refined[..., 1]], -1), atol=1e-12)


def test_flatten_order_is_coherent():
    rng = np.random.default_rng(6)
    position = rng.random((256, 3))
    normal = np.tile([0.0, 0.0, 1.0], (256, 1))
    order = flatten_order(position, normal, diagonal=math.sqrt(3))
    assert sorted(order.tolist()) == list(range(256))
    texture = position[order].reshape(16, 16, 3)
    # Each 2 x 2 Haar cell groups near samples: far closer than random pairs.
    cell_spread = np.linalg.norm(texture[0::2, 0::2] - texture[1::2, 1::2], axis=-1).mean()
    random_spread = np.linalg.norm(position - position[rng.permutation(256)], axis=-1).mean()
    assert cell_spread < 0.35 * random_spread


def _gathers(position, normal, area) -> GatherSamples:
    num = len(position)
    return GatherSamples(
        position=torch.tensor(position),
        normal=torch.tensor(normal),
        albedo=torch.full((num, 3), 0.5),
        emission=torch.zeros(num, 3),
        area=torch.tensor(area),
    )


def test_transport_term_is_the_clamped_disc_form_factor():
    # A receiver at the origin facing +z; gathers above it facing down, one behind a blocker. Area 0.5:
    # disc radius 0.40, so gathers beyond NEAR_RADII radii (2.4) take the clamped point term.
    gathers = _gathers(
        [[0.0, 0, 4], [3.0, 0, 2], [0, 0, -4], [0, 0, 8]],
        [[0.0, 0, -1], [0, 0, -1], [0, 0, 1], [0, 0, 1]],
        [0.5, 0.5, 0.5, 0.5],
    )
    blocker = np.array([[[1.0, -1, 1], [2.0, -1, 1], [1.5, 1, 1]]], np.float32)  # crosses the ray to (3, 0, 2)
    caster = EmbreeCaster(blocker)
    wi, weight = gather_transport(torch.zeros(1, 3), torch.tensor([[0.0, 0, 1]]), gathers, caster)
    torch.testing.assert_close(wi[0, 0], torch.tensor([0.0, 0, 1]))
    assert weight[0, 0].item() == pytest.approx(0.5 / (16 + 0.5 / math.pi), rel=1e-6)
    assert weight[0, 1].item() == 0.0  # blocked
    assert weight[0, 2].item() == 0.0  # behind the receiver
    assert weight[0, 3].item() == 0.0  # facing away


@pytest.mark.parametrize("height_in_radii", [0.5, 1.0, 3.0, 5.0])
def test_near_gathers_integrate_their_disc(height_in_radii):
    # A coaxial disc of radius R at height h over a receiver facing it: the integral of
    # cos cos / r^2 over the disc is pi R^2 / (h^2 + R^2) (the form factor times pi). Closer than
    # half a radius the disc's points, each with its own clamp, read low (0.54 for pi at 0.05 R):
    # there the light concentrates within h of the axis, finer than the points.
    area = 0.5
    radius_squared = area / math.pi
    height = height_in_radii * math.sqrt(radius_squared)
    gathers = _gathers([[0.0, 0, height], [0, 0, -9], [0, 0, -9], [0, 0, -9]], [[0.0, 0, -1]] * 4, [area] * 4)
    _, weight = gather_transport(
        torch.zeros(1, 3), torch.tensor([[0.0, 0, 1]]), gathers, EmbreeCaster(np.zeros((0, 3, 3), np.float32))
    )
    exact = math.pi * radius_squared / (height**2 + radius_squared)
    assert weight[0, 0].item() == pytest.approx(exact, rel=0.05)


def test_near_gathers_at_a_corner_reach_the_receiver():
    # A receiver on a floor next to a wall, a gather on the wall just above the corner: the point
    # term sees it edge-on at a grazing angle; integrated over its disc it carries the light the
    # corner's form factor holds (a numerical integral over the same disc, 400 x 400 points).
    area = 0.04
    gathers = _gathers([[0.0, 0.15, 0.0]] + [[0.0, -9, 0]] * 3, [[1.0, 0, 0]] * 4, [area] * 4)  # wall x = 0
    receiver = torch.tensor([[0.05, 0.0, 0.0]])
    _, weight = gather_transport(
        receiver, torch.tensor([[0.0, 1.0, 0]]), gathers, EmbreeCaster(np.zeros((0, 3, 3), np.float32))
    )
    radius = math.sqrt(area / math.pi)
    side = torch.linspace(-radius, radius, 400, dtype=torch.float64)
    y, z = torch.meshgrid(side, side, indexing="ij")
    inside = y**2 + z**2 <= radius**2
    points = torch.stack((torch.zeros_like(y), 0.15 + y, z), -1)[inside & (0.15 + y > 0)]
    offset = points - receiver.double()
    distance_squared = (offset**2).sum(-1)
    cos_gather = -offset[:, 0] / distance_squared.sqrt()
    cos_receiver = offset[:, 1] / distance_squared.sqrt()
    cell = (2 * radius / 399) ** 2
    exact = float((cos_gather * cos_receiver / distance_squared).sum() * cell)
    wi, _ = gather_transport(
        receiver, torch.tensor([[0.0, 1.0, 0]]), gathers, EmbreeCaster(np.zeros((0, 3, 3), np.float32))
    )
    assert weight[0, 0].item() * wi[0, 0, 1].item() == pytest.approx(exact, rel=0.1)


def test_gather_radiance_under_a_point_light():
    # L = albedo / pi * I / d^2 for a gather facing a point light (normalized radius-0 sphere: I = intensity / 4).
    gathers = _gathers(
        [[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 0]], [[0.0, 0, 1], [0, 0, 1], [0, 0, -1], [0, 0, 1]], [1.0] * 4
    )
    transform = np.eye(4)
    transform[:3, 3] = [0.0, 0.0, 2.0]
    light = Light(
        path="/L", kind=LightKind.SPHERE, world_from_light=transform, radius=0.0, normalize=True, intensity=8.0
    )
    visibility = RayVisibility(EmbreeCaster(np.zeros((0, 3, 3), np.float32)))
    radiance = gather_radiance(light, gathers, visibility, num_samples=1)
    intensity = 2.0
    expected_0 = 0.5 / math.pi * intensity / 4.0
    cos_1, d2_1 = 2 / math.sqrt(5), 5.0
    torch.testing.assert_close(radiance[0], torch.full((3,), expected_0))
    torch.testing.assert_close(radiance[1], torch.full((3,), 0.5 / math.pi * intensity * cos_1 / d2_1))
    assert radiance[2].abs().max() == 0.0  # faces away


def test_disc_support_clips_a_gather_disc_to_its_surface():
    # A gather on the edge x = 0 of a floor quad [0, 1]^2 (z = 0): the half of its disc over x < 0
    # stands for area that does not exist, the half over the quad for the floor.
    floor = np.array([[[0.0, 0, 0], [1, 0, 0], [1, 1, 0]], [[0.0, 0, 0], [1, 1, 0], [0, 1, 0]]], np.float32)
    gathers = _gathers([[0.0, 0.5, 0], [0.5, 0.5, 0], [0.5, 0.2, 0], [0.3, 0.6, 0]], [[0.0, 0, 1]] * 4, [0.04] * 4)
    support = disc_support(gathers, EmbreeCaster(floor))
    pattern_x = disc_points(gathers, torch.tensor([0]))[0, :, 0]
    assert torch.equal(support[0], pattern_x > 0)  # no pattern point lies on the edge itself
    assert support[1:].all()  # discs inside the quad are whole
