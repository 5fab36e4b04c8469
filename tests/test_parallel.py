"""Coarse-grained CPU parallelism (`relight_torch.parallel`): results in order on worker threads,
errors re-raised, no nested fan-out, torch's thread count restored; and the direct relighter's
tiles of points on workers give the image one tile gives."""

from __future__ import annotations

import threading

import pytest
import torch

from cache_support import bake_bundled
from relight_torch.direct.relighter import open_relighter
from relight_torch.direct.settings import RelightSettings
from relight_torch.parallel import in_worker, parallel_map, tile_threads, torch_threads


def test_parallel_map_keeps_order_on_workers_and_restores_torch_threads():
    before = torch.get_num_threads()
    names = parallel_map(
        lambda item: (item, threading.current_thread().name, in_worker(), torch.get_num_threads()), list(range(6)), 2
    )
    assert [item for item, *_ in names] == list(range(6))
    assert all(name.startswith("relight") and worker and threads == 1 for _, name, worker, threads in names)
    assert torch.get_num_threads() == before and not in_worker()
    # Inside a worker nothing fans out again: the items run in turn on that worker.
    nested = parallel_map(lambda _: parallel_map(lambda _: threading.current_thread().name, [0, 1], 2), [0], 2)
    assert len(set(nested[0])) == 1
    assert (
        parallel_map(lambda item: threading.current_thread().name, [0, 1], 1) == [threading.current_thread().name] * 2
    )


def test_parallel_map_reraises_a_pieces_error():
    def piece(item: int) -> int:
        if item == 3:
            raise ValueError("piece 3")
        return item

    with pytest.raises(ValueError, match="piece 3"):
        parallel_map(piece, list(range(5)), 2)


def test_tile_threads():
    with torch_threads(2):
        assert tile_threads(torch.device("cpu")) == 2
        assert tile_threads(torch.device("cpu"), thread_safe=False) == 1
        assert tile_threads(torch.device("cuda")) == 1
        assert parallel_map(lambda _: tile_threads(torch.device("cpu")), [0, 1], 2) == [1, 1]


def test_tiles_of_points_give_the_image_of_one_tile(tmp_path):
    layer = bake_bundled("cornell_box", tmp_path)
    settings = RelightSettings(area_samples=4, shadow_filter_radius=1)
    with torch_threads(1):
        whole = open_relighter(layer, settings=settings)
        expected = whole.render()
    with torch_threads(2):
        tiled = open_relighter(layer, settings=settings)
        image = tiled.render()
    torch.testing.assert_close(image, expected, rtol=1e-5, atol=1e-7)
    assert tiled.visibility.num_rays == whole.visibility.num_rays > 0
