"""The Embree caster's memory: a soup added as indexed blocks (`shared_corners`) traces exactly as
one soup mesh does, a memory-mapped soup's pages are given back once Embree holds its copy, and a
shadow link's caster is built over a selection without copying the triangles."""

from __future__ import annotations

import numpy as np
import pytest
from embreex import mesh_construction, rtcore_scene

from relight_torch.io.mapped import map_array, release_pages
from relight_torch.visibility import embree
from relight_torch.visibility.embree import EmbreeCaster, ShadowLinkCasters, shared_corners


def grid_soup(rng, num_quads: int = 24) -> np.ndarray:
    """(T, 3, 3) float32 soup of a jittered height field: every inner corner shared by 6 triangles."""
    x, z = np.meshgrid(np.linspace(-1, 1, num_quads + 1), np.linspace(-1, 1, num_quads + 1))
    points = np.stack([x, rng.uniform(-0.2, 0.2, x.shape), z], axis=-1).astype(np.float32)
    a, b, c, d = points[:-1, :-1], points[:-1, 1:], points[1:, :-1], points[1:, 1:]
    return np.concatenate([np.stack([a, b, c], -2).reshape(-1, 3, 3), np.stack([b, d, c], -2).reshape(-1, 3, 3)])


def random_rays(rng, num_rays: int = 3000):
    origins = np.concatenate(
        [
            rng.uniform(-1.2, 1.2, (num_rays, 1)),
            rng.uniform(0.5, 1.5, (num_rays, 1)),
            rng.uniform(-1.2, 1.2, (num_rays, 1)),
        ],
        axis=1,
    ).astype(np.float32)
    directions = (rng.uniform(-1, 1, (num_rays, 3)) * [0.5, 1, 0.5] - [0, 1.5, 0]).astype(np.float32)
    return origins, directions, rng.uniform(0.2, 2.0, num_rays).astype(np.float32)


def flat_embree_hits(corners, origins, directions):
    """Twin: the closest hits of embreex's own soup mesh (one geometry, 3 vertices a triangle)."""
    scene = rtcore_scene.EmbreeScene(robust=True)
    mesh_construction.TriangleMesh(scene, corners)
    raw = scene.run(origins, directions, dists=np.full(origins.shape[0], np.inf, np.float32), output=1)
    return raw["primID"], raw["tfar"], np.stack([raw["u"], raw["v"]], -1)


def test_shared_corners_index_the_same_bits():
    rng = np.random.default_rng(0)
    soup = grid_soup(rng)
    soup[0, 0] = [0.0, 0.0, 0.0]
    soup[1, 0] = [-0.0, 0.0, 0.0]  # another bit pattern: stays another vertex
    vertices, triangles = shared_corners(soup)
    assert vertices.dtype == np.float32 and triangles.dtype == np.int32 and triangles.shape == (soup.shape[0], 3)
    assert np.array_equal(vertices[triangles].view(np.uint32), soup.view(np.uint32))
    assert len({tuple(v) for v in vertices.view(np.uint32)}) == vertices.shape[0]  # no bits twice
    assert vertices.shape[0] <= 26 * 26 + 1 < soup.shape[0]  # the grid's corners (and the -0.0)


@pytest.mark.parametrize("block", [7, 1 << 20])
def test_blocks_of_indexed_meshes_trace_as_one_soup(monkeypatch, block):
    rng = np.random.default_rng(1)
    soup = grid_soup(rng)
    origins, directions, t_far = random_rays(rng)
    prim, distance, barycentrics = flat_embree_hits(soup, origins, directions)
    monkeypatch.setattr(embree, "BUILD_BLOCK_TRIANGLES", block)
    caster = EmbreeCaster(soup, num_threads=1)
    hits = caster.intersect(origins, directions)
    assert 0.5 < hits.hit.mean() < 1.0
    np.testing.assert_array_equal(hits.triangle_id, prim)
    np.testing.assert_array_equal(hits.distance[hits.hit], distance[prim >= 0])
    np.testing.assert_array_equal(hits.barycentrics[hits.hit], barycentrics[prim >= 0])
    expected_blocked = np.where(prim >= 0, distance, np.inf) <= t_far
    np.testing.assert_array_equal(caster.occluded(origins, directions, t_far), expected_blocked)
    points = soup.reshape(-1, 3).astype(np.float64)
    diagonal = np.linalg.norm(points.max(0) - points.min(0))
    assert caster.epsilon == pytest.approx(embree.EPSILON_DIAGONAL_FRACTION * diagonal)


def mapped_rss_kb(path) -> int:
    """Resident kilobytes of this process's mappings of `path` (/proc/self/smaps)."""
    total, inside = 0, False
    with open("/proc/self/smaps") as smaps:
        for line in smaps:
            fields = line.split()
            if "-" in fields[0] and not fields[0].endswith(":"):
                inside = len(fields) >= 6 and fields[-1] == str(path)
            elif inside and fields[0] == "Rss:":
                total += int(fields[1])
    return total


def test_a_mapped_soup_is_not_kept_resident(tmp_path, monkeypatch):
    rng = np.random.default_rng(2)
    soup = np.concatenate([grid_soup(rng, 64)] * 8)  # 65536 triangles, 2.4 MB
    path = tmp_path / "occluders.npy"
    np.save(path, soup)
    with open(path, "rb") as handle:
        mapped = map_array(handle, soup.shape, soup.dtype, 128, False)
    assert np.array_equal(mapped, soup)
    assert mapped_rss_kb(path) >= soup.nbytes // 1024  # reading it made it resident
    release_pages(mapped)
    assert mapped_rss_kb(path) == 0
    monkeypatch.setattr(embree, "BUILD_BLOCK_TRIANGLES", 10000)
    caster = EmbreeCaster(mapped, num_threads=1)
    assert mapped_rss_kb(path) == 0  # Embree copied it block by block and gave the pages back
    origins, directions, _ = random_rays(rng, 500)
    expected = EmbreeCaster(soup, num_threads=1).intersect(origins, directions)
    np.testing.assert_array_equal(caster.intersect(origins, directions).triangle_id, expected.triangle_id)


def test_release_pages_leaves_ordinary_arrays_alone():
    values = np.arange(10.0)
    release_pages(values)
    release_pages(values[2:5])
    assert np.array_equal(values, np.arange(10.0))


def test_a_shadow_link_caster_traces_its_objects_only():
    rng = np.random.default_rng(3)
    soup = grid_soup(rng)
    objects = (np.arange(soup.shape[0]) % 3 == 0).astype(np.int32)  # object 1: every third triangle
    origins, directions, t_far = random_rays(rng)
    links = ShadowLinkCasters(soup, objects, ["/Ground", "/Rocks"], epsilon=1e-4)
    linked = links(("/Rocks",))
    subset = EmbreeCaster(np.ascontiguousarray(soup[objects == 1]), num_threads=1, epsilon=1e-4)
    hits, expected = linked.intersect(origins, directions), subset.intersect(origins, directions)
    assert 0.2 < hits.hit.mean() < 0.8
    np.testing.assert_array_equal(hits.triangle_id, expected.triangle_id)  # ids into the link's triangles
    np.testing.assert_array_equal(hits.distance, expected.distance)
    np.testing.assert_array_equal(
        linked.occluded(origins, directions, t_far), subset.occluded(origins, directions, t_far)
    )
    assert links(("/Rocks",)) is linked and linked.epsilon == 1e-4
