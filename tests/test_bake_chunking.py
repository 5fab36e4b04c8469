"""The direct bake's chunks hold a bounded number of sub-samples whatever the image width (a wide
image once made each 64-row band three times the memory of a 640-pixel one)."""

from pipeline.bake.direct.bake import SUBSAMPLES_PER_CHUNK, rows_per_chunk


def test_chunk_sub_samples_do_not_grow_with_the_width():
    for width in (16, 640, 1920, 4096):
        for supersampling in (1, 2, 4):
            rows = rows_per_chunk(width, supersampling)
            assert rows >= 1
            assert rows * width * supersampling**2 <= SUBSAMPLES_PER_CHUNK
            assert (rows + 1) * width * supersampling**2 > SUBSAMPLES_PER_CHUNK
    assert rows_per_chunk(1 << 20, 4) == 1  # a single row wider than a chunk is still one chunk
