"""The scene's nadir height map (DSM), rendered tile by tile through the tile renderer's depth pass."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from concurrent.futures import Executor

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


def dsm_tiles(grid: Grid, tile_px: int = DSM_TILE_PX) -> list[tuple[int, int, int, int]]:
    """(row, col, height, width) of each ``tile_px`` render tile of ``grid``, row by row."""
    return [(r0, c0, min(tile_px, grid.height - r0), min(tile_px, grid.width - c0))
            for r0 in range(0, grid.height, tile_px) for c0 in range(0, grid.width, tile_px)]


def height_map_tiles(chunks: list[tuple[np.ndarray, Callable[[], tuple[np.ndarray, list]]]], grid: Grid,
                     tile_px: int = DSM_TILE_PX, pool: Executor | None = None,
                     ahead: int = 1) -> Iterator[tuple[int, int, np.ndarray]]:
    """(row, col, heights) of each ``tile_px`` render tile of ``grid``, row by row: the top-surface
    height (float64, NaN where no model) at its cell centres.

    A tile loads only the chunks whose footprint touches it, so memory stays O(tile). With
    ``pool`` (forked workers, :func:`~pipeline25d.core.cores.fork_pool`; ``load`` must then
    pickle, as :func:`~pipeline25d.stages.lod.chunk_loaders`' do) the tiles are rendered there,
    ``ahead`` at a time, each on its worker's own GL context: the same heights.
    """
    from pipeline25d.core.cores import map_ahead

    tiles = dsm_tiles(grid, tile_px)
    if not chunks:
        yield from ((r0, c0, np.full((h, w), np.nan)) for r0, c0, h, w in tiles)
        return
    zlo = min(b[0][2] for b, _ in chunks) - NADIR_MARGIN_M
    zhi = max(b[1][2] for b, _ in chunks) + NADIR_MARGIN_M
    work = []
    for r0, c0, h, w in tiles:
        ext = grid.window(slice(r0, r0 + h), slice(c0, c0 + w)).bounds
        touching = [(b, load) for b, load in chunks
                    if b[0][0] <= ext.xmax and b[1][0] >= ext.xmin and b[0][1] <= ext.ymax and b[1][1] >= ext.ymin]
        work.append((touching, ext, (w, h), (-zhi, -zlo)))      # nadir depth is −z: near = the highest surface
    drawn = [args for args in work if args[0]]
    if pool is None:
        heights = _rendered_here(drawn)
    else:
        heights = map_ahead(pool, tile_heights, drawn, ahead)
    for (r0, c0, h, w), (touching, *_) in zip(tiles, work):
        yield r0, c0, next(heights) if touching else np.full((h, w), np.nan)


def _rendered_here(work: list[tuple]) -> Iterator[np.ndarray]:
    """:func:`tile_heights` of each of ``work``, on one GL context of this process."""
    from pipeline25d.stages.render import TileRenderer, create_context

    ctx = create_context()
    try:
        renderer = TileRenderer(ctx, samples=0)
        for args in work:
            yield tile_heights(*args, renderer=renderer)
    finally:
        ctx.release()


def tile_heights(chunks: list[tuple[np.ndarray, Callable[[], tuple[np.ndarray, list]]]], ext, size: tuple[int, int],
                 depth_range: tuple[float, float], renderer=None) -> np.ndarray:
    """(h, w) top-surface heights of the ``chunks`` (bounds, load) over extent ``ext``, ``size``
    (w, h) cells, nadir depths within ``depth_range``; on ``renderer``, else on a GL context
    made for this tile (a worker process's)."""
    from pipeline25d.geometry.perspectives import Perspective
    from pipeline25d.stages.render import TileRenderer, TileView, create_context

    if renderer is None:
        ctx = create_context()
        try:
            return tile_heights(chunks, ext, size, depth_range, TileRenderer(ctx, samples=0))
        finally:
            ctx.release()
    todo = [load() for _, load in chunks]
    view = TileView(Perspective(0, 90), 0.0, ext, depth_range, size)
    return -renderer.render_depth(todo, view)
