"""A frame's fixed memory: the same-surface filter keeps one bool mask per axis and offset (not
float32 weights plus per-tile copies) with the numbers of a per-pixel loop, and the fixed light
samples are made one sample at a time with the numbers of the all-at-once formula."""

from __future__ import annotations

import math

import numpy as np
import torch

from relight_torch.brdf.preview_surface import PreviewSurfaceParams
from relight_torch.gbuffer import GBuffer
from relight_torch.light_samples import fixed_light_samples, point_rotations, sample_pattern
from relight_torch.visibility import surface_filter
from relight_torch.visibility.surface_filter import SurfaceFilter

HEIGHT, WIDTH = 21, 30


def step_gbuffer() -> GBuffer:
    """A floor (y = 0) with a raised block (y = 0.3) over its right third, a curved strip, and
    an uncovered hole: neighbours across the step or the hole are another surface."""
    rows, columns = np.mgrid[0:HEIGHT, 0:WIDTH]
    x, z = columns / WIDTH, rows / HEIGHT
    y = np.where(columns >= 20, 0.3, 0.0) + np.where(rows < 4, 0.8 * x**2, 0.0)
    position = np.stack([x, y, z], -1).reshape(-1, 3)
    normal = np.stack([np.where(rows < 4, -1.6 * x, 0.0), np.ones_like(x), np.zeros_like(x)], -1).reshape(-1, 3)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    covered = ~((rows >= 8) & (rows < 11) & (columns >= 5) & (columns < 9)).reshape(-1)
    index = np.flatnonzero(covered)
    count = index.size
    params = PreviewSurfaceParams.from_numpy(
        {
            **{name: np.full((count, 3), 0.5) for name in ("diffuse_color", "emissive_color", "specular_color")},
            **{name: np.zeros(count) for name in ("metallic", "clearcoat", "use_specular_workflow")},
            **{name: np.full(count, 0.5) for name in ("roughness", "clearcoat_roughness", "ior", "opacity")},
        }
    )
    frame = np.zeros((count, 3), np.float32)
    return GBuffer.from_numpy(
        (HEIGHT, WIDTH),
        index,
        params,
        np.zeros(3),
        position=position[index].astype(np.float32),
        normal=normal[index].astype(np.float32),
        tangent=frame,
        bitangent=frame,
        geometric_normal=normal[index].astype(np.float32),
        material_id=np.zeros(count, np.int32),
        object_id=np.zeros(count, np.int32),
        depth=np.ones(count, np.float32),
    )


def loop_filter(gbuffer: GBuffer, values: np.ndarray, radius: int) -> np.ndarray:
    """Slow twin of `SurfaceFilter.__call__`: per pixel, a horizontal then a vertical sum over the
    neighbours on the same surface (the module doc's tests, written out pair by pair)."""
    height, width = gbuffer.image_size
    position = np.full((height * width, 3), np.nan)
    normal = np.full((height * width, 3), np.nan)
    image = np.zeros((height * width, values.shape[1]))
    index = gbuffer.pixel_index.numpy()
    position[index], normal[index], image[index] = gbuffer.position.numpy(), gbuffer.normal.numpy(), values
    position, normal = position.reshape(height, width, 3), normal.reshape(height, width, 3)
    image = image.reshape(height, width, -1)

    def same(p, q) -> bool:
        if np.isnan(position[p][0]) or np.isnan(position[q][0]):
            return False
        between = position[q] - position[p]
        return float(normal[p] @ normal[q]) >= surface_filter.MIN_NORMAL_COSINE and abs(
            float(between @ normal[p])
        ) <= surface_filter.MAX_PLANE_SLOPE * float(np.linalg.norm(between))

    for axis in (1, 0):
        total = image.copy()
        for row in range(height):
            for column in range(width):
                for offset in range(-radius, radius + 1):
                    other = (row, column + offset) if axis == 1 else (row + offset, column)
                    inside = 0 <= other[0] < height and 0 <= other[1] < width
                    if offset and inside and same((row, column), other):
                        total[row, column] += image[other]
        image = total
    return image.reshape(height * width, -1)[index]


def test_the_filter_matches_its_per_pixel_loop_and_keeps_bool_masks():
    gbuffer = step_gbuffer()
    values = torch.rand(gbuffer.num_samples, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    radius = 3
    chosen = SurfaceFilter(gbuffer, radius)
    filtered = chosen(values.to(torch.float32))
    expected = loop_filter(gbuffer, values.numpy(), radius)
    np.testing.assert_allclose(filtered.numpy(), expected, rtol=1e-5)
    assert float(expected[:, 0].min()) > 0 and not np.allclose(expected[:, 0], expected[:, 0].max())
    # 4r bool masks over the padded tile grid, nothing per tile.
    assert all(mask.dtype == torch.bool for mask in chosen.masks)
    padded = (math.ceil(HEIGHT / chosen.tile) * chosen.tile + 2 * radius) * (
        math.ceil(WIDTH / chosen.tile) * chosen.tile + 2 * radius
    )
    assert sum(mask.numel() * mask.element_size() for mask in chosen.masks) == 4 * radius * padded
    assert set(vars(chosen)) == {"gbuffer", "radius", "tile", "masks"}


def test_the_tiled_visibility_matches_the_whole_filter_across_tile_edges(monkeypatch):
    monkeypatch.setattr(surface_filter, "TILE", 4)
    monkeypatch.setattr(surface_filter, "MAX_TILE_FRACTION", 1.0)  # tiles however many
    gbuffer = step_gbuffer()
    chosen = SurfaceFilter(gbuffer, 3)
    generator = torch.Generator().manual_seed(1)
    weights = torch.rand(gbuffer.num_samples, generator=generator) + 0.1
    lit = (torch.rand(gbuffer.num_samples, generator=generator) < 0.7).to(weights.dtype)
    sums = torch.stack((weights * lit, weights), dim=-1)
    whole = chosen(sums)
    expected = torch.where(whole[:, 1] > 0, whole[:, 0] / whole[:, 1], 0.0)
    torch.testing.assert_close(chosen.visibility(sums), expected, rtol=1e-6, atol=1e-7)


def all_at_once(num_points: int, num_samples: int, seed: int) -> torch.Tensor:
    """Twin of `fixed_light_samples`: the rotations added to the whole (S, N, 2) pattern in one go."""
    pattern, rotation = sample_pattern(num_samples, seed), point_rotations(num_points, seed)
    u = torch.remainder(pattern.unsqueeze(1) + rotation.unsqueeze(0), 1.0)
    return u.clamp(max=1.0 - 1e-7).to(torch.float32).transpose(0, 1)


def test_fixed_light_samples_made_one_sample_at_a_time_are_the_same_numbers():
    for num_points, num_samples, seed in ((1000, 16, 0), (777, 7, 3), (5, 1, 1)):
        expected = all_at_once(num_points, num_samples, seed)
        samples = fixed_light_samples(num_points, num_samples, seed)
        assert torch.equal(samples, expected) and samples.stride() == expected.stride()
    # The numbers the relighter has always used: the seed's first draws are the rotations.
    first = torch.rand((3, 1, 2), generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    expected = torch.remainder(torch.full((1, 1, 2), 0.5, dtype=torch.float64) + first, 1.0).to(torch.float32)
    assert torch.equal(fixed_light_samples(3, 1, 0), expected)
