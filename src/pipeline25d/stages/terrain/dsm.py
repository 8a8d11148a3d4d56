"""The scene's nadir height map (DSM), rendered tile by tile through the tile renderer's depth pass."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator

import numpy as np

from pipeline25d.core.grid import Grid

log = logging.getLogger(__name__)


DSM_TILE_PX = 2048          # render tile edge of the DSM pass


MAX_DSM_CELLS = 16_000_000  # the auto resolution coarsens until the DSM has at most this many cells


NADIR_MARGIN_M = 1.0        # depth-range margin of the nadir pass


def auto_resolution(bounds_xy: tuple[float, float, float, float], gsd: float) -> float:
    """DSM/DTM cell size: 2·gsd clamped to [0.5, 5] m, coarsened to keep the grid under MAX_DSM_CELLS."""
    res = min(max(2.0 * gsd, 0.5), 5.0)
    area = (bounds_xy[2] - bounds_xy[0]) * (bounds_xy[3] - bounds_xy[1])
    while area / res ** 2 > MAX_DSM_CELLS:
        res *= 2
    return res


def render_height_map(chunks: list[tuple[np.ndarray, Callable[[], tuple[np.ndarray, list]]]], grid: Grid,
                      tile_px: int = DSM_TILE_PX) -> np.ndarray:
    """Top-surface height (float64, NaN where no model) at every cell centre of ``grid``.

    ``chunks``: (bounds (2, 3), load) per chunk, load() -> (origin, parts); see :func:`height_map_tiles`.
    """
    out = np.full(grid.shape, np.nan)
    for r0, c0, heights in height_map_tiles(chunks, grid, tile_px):
        out[r0:r0 + heights.shape[0], c0:c0 + heights.shape[1]] = heights
    return out


def height_map_tiles(chunks: list[tuple[np.ndarray, Callable[[], tuple[np.ndarray, list]]]], grid: Grid,
                     tile_px: int = DSM_TILE_PX) -> Iterator[tuple[int, int, np.ndarray]]:
    """(row, col, heights) of each ``tile_px`` render tile of ``grid``, row by row: the top-surface
    height (float64, NaN where no model) at its cell centres.

    A tile loads only the chunks whose footprint touches it, so memory stays O(tile).
    """
    tiles = [(r0, c0, min(tile_px, grid.height - r0), min(tile_px, grid.width - c0))
             for r0 in range(0, grid.height, tile_px) for c0 in range(0, grid.width, tile_px)]
    if not chunks:
        yield from ((r0, c0, np.full((h, w), np.nan)) for r0, c0, h, w in tiles)
        return
    from pipeline25d.geometry.perspectives import Perspective
    from pipeline25d.stages.render import TileRenderer, TileView, create_context

    nadir = Perspective(0, 90)
    zlo = min(b[0][2] for b, _ in chunks) - NADIR_MARGIN_M
    zhi = max(b[1][2] for b, _ in chunks) + NADIR_MARGIN_M
    ctx = create_context()
    try:
        renderer = TileRenderer(ctx, samples=0)
        for r0, c0, h, w in tiles:
            ext = grid.window(slice(r0, r0 + h), slice(c0, c0 + w)).bounds
            todo = [load() for b, load in chunks
                    if b[0][0] <= ext.xmax and b[1][0] >= ext.xmin and b[0][1] <= ext.ymax and b[1][1] >= ext.ymin]
            if not todo:
                yield r0, c0, np.full((h, w), np.nan)
                continue
            # nadir depth is −z: near = the highest surface
            view = TileView(nadir, 0.0, ext, (-zhi, -zlo), (w, h))
            heights = -renderer.render_depth(todo, view)
            del todo
            yield r0, c0, heights
    finally:
        ctx.release()
