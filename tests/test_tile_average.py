"""A base tile's average (stages.tiles.base.average_tile) against its definition: the window upsampled
by nearest neighbour to gdal2tiles' 4x query, then averaged 4 x 4 with GDAL's rounding, for whole
windows (the fast path) and windows clipped at the query's edge (the general one)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline25d.stages.tiles.base import average_tile, nearest_index

QUERY, TILE = 1024, 256


def by_definition(data: np.ndarray, wx: int, wy: int, wxsize: int, wysize: int) -> np.ndarray:
    rows, cols = nearest_index(data.shape[1], wysize), nearest_index(data.shape[2], wxsize)
    query = np.zeros((data.shape[0], QUERY, QUERY), np.int64)
    query[:, wy:wy + wysize, wx:wx + wxsize] = data[:, rows][:, :, cols]
    total = query.reshape(data.shape[0], TILE, 4, TILE, 4).sum(axis=(2, 4))
    return ((total + 8) // 16).astype(np.uint8)


@pytest.mark.parametrize("n", [256, 512, 1024, 2048, 300, 777])
def test_a_whole_window_is_averaged_as_its_query(n):
    data = np.random.default_rng(n).integers(0, 256, (4, n, n), dtype=np.uint8)
    data[:, : n // 3] = 255                                # saturated sums must not overflow
    idx = nearest_index(n, QUERY)
    assert np.array_equal(average_tile(data, idx, idx, 0, 0, QUERY, TILE), by_definition(data, 0, 0, QUERY, QUERY))


@pytest.mark.parametrize("shape,offset,size", [((4, 512, 300), (600, 0), (424, 1024)),
                                               ((4, 200, 512), (0, 640), (1024, 384)),
                                               ((4, 130, 70), (3, 5), (140, 260))])
def test_a_window_clipped_at_the_query_edge_is_averaged_as_its_query(shape, offset, size):
    data = np.random.default_rng(7).integers(0, 256, shape, dtype=np.uint8)
    (wx, wy), (wxsize, wysize) = offset, size
    rows, cols = nearest_index(shape[1], wysize), nearest_index(shape[2], wxsize)
    got = average_tile(data, rows, cols, wx, wy, QUERY, TILE)
    assert np.array_equal(got, by_definition(data, wx, wy, wxsize, wysize))
