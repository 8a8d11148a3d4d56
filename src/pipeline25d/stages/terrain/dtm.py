"""The DTM between ground cells: GDAL's inverse-distance fill corrected by local planes
(:mod:`~pipeline25d.stages.terrain.gap_planes`), block by block, only where it is needed."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from concurrent.futures import Executor

import numpy as np

from pipeline25d.core.grid import BLOCK_CELLS, Block, Grid, cell_blocks, widen
from pipeline25d.core.raster import fill_nearest, gdal

log = logging.getLogger(__name__)


def interpolate_dtm(seed: np.ndarray, search_cells: int, reach_cells: float | None = None,
                    plane_cells: int = 0) -> np.ndarray:
    """Fill the NaN cells of ``seed`` (ground heights) with GDAL's inverse-distance FillNodata,
    corrected by the local planes of boxes ``plane_cells`` cells round each gap cell (0: none;
    :func:`~pipeline25d.stages.terrain.gap_planes.plane_corrected`).

    The search reaches ``search_cells`` (half the widest object is enough); cells beyond it
    take their nearest value, up to ``reach_cells`` from it (default: everywhere; beyond, NaN:
    empty land far from any model needs no DTM). A change to the ground therefore alters the
    DTM only within that reach, which keeps district updates local.
    """
    if not np.isfinite(seed).any():
        raise ValueError("no ground cells to build a DTM from")
    return fill_nearest(_filled(seed, search_cells, plane_cells), reach_cells)


def fill_reach(search_cells: int, plane_cells: int = 0) -> int:
    """Cells of the ground heights (rows and columns) a cell of the fill depends on."""
    from pipeline25d.stages.terrain.gap_planes import plane_reach

    return max(int(search_cells), 1, plane_reach(plane_cells) if plane_cells else 0)


def _filled(seed: np.ndarray, search_cells: int, plane_cells: int = 0) -> np.ndarray:
    """:func:`_fill_nodata`, then the local planes' correction (``plane_cells`` > 0)."""
    filled = _fill_nodata(seed, search_cells)
    if not plane_cells:
        return filled
    from pipeline25d.stages.terrain.gap_planes import plane_corrected

    return plane_corrected(seed, filled, int(plane_cells), _fill_nodata)


def _fill_nodata(seed: np.ndarray, search_cells: int) -> np.ndarray:
    """FillNodata's inverse-distance fill of ``seed`` within ``search_cells`` (NaN beyond).

    A cell depends only on the seed within ``search_cells`` rows and columns of it, so only
    the windows around groups of seed cells are filled (:func:`near_windows`; a sparse window
    is mostly empty land, where FillNodata would search the whole distance from every cell
    for nothing).
    """
    out = np.full(seed.shape, np.nan)
    for window, take in near_windows(np.isfinite(seed), max(int(search_cells), 1) + 1):
        out[window][take] = _fill_window(seed[window], search_cells)[take]
    return out


def near_windows(mask: np.ndarray, reach: int, cell: int = 64) -> list[tuple[tuple[slice, slice], np.ndarray]]:
    """The windows of an array where something is within ``reach`` cells of ``mask``'s True cells.

    The array is cut into squares of ``cell`` cells; the squares within ``reach`` (rows and
    columns) of a True cell are grouped by 8-connectivity. Each group gives (window, take):
    its bounding box grown by ``reach`` (within the array) and, on that window, its own
    cells. Every True cell within ``reach`` of a taken cell lies in the window, so anything
    that looks no farther than ``reach`` computed on the window alone is exact on the taken
    cells; a cell that no group takes is farther than ``reach`` from every True cell. A
    sparse scene's few districts thus cost their surroundings, not the empty land between.
    """
    from scipy import ndimage as ndi

    h, w = mask.shape
    nr, nc = -(-h // cell), -(-w // cell)
    padded = np.zeros((nr * cell, nc * cell), bool)
    padded[:h, :w] = mask
    squares = padded.reshape(nr, cell, nc, cell).any(axis=(1, 3))
    k = -(-int(reach) // cell)
    kept = ndi.binary_dilation(squares, np.ones((2 * k + 1, 2 * k + 1), bool)) if squares.any() else squares
    labels, _ = ndi.label(kept, np.ones((3, 3), bool))
    cell_labels = np.repeat(np.repeat(labels, cell, axis=0), cell, axis=1)[:h, :w]      # each cell's group
    out = []
    for label, (rs, cs) in enumerate(ndi.find_objects(labels), 1):
        window = (slice(max(rs.start * cell - reach, 0), min(rs.stop * cell + reach, h)),
                  slice(max(cs.start * cell - reach, 0), min(cs.stop * cell + reach, w)))
        out.append((window, cell_labels[window] == label))
    return out


def _fill_window(seed: np.ndarray, search_cells: int) -> np.ndarray:
    g = gdal()
    h, w = seed.shape
    nodata = -1e30
    ds = g.GetDriverByName("MEM").Create("", w, h, 1, g.GDT_Float64)
    band = ds.GetRasterBand(1)
    band.SetNoDataValue(nodata)
    band.WriteArray(np.where(np.isfinite(seed), seed, nodata))
    g.FillNodata(band, None, maxSearchDist=max(int(search_cells), 1), smoothingIterations=0)
    out = band.ReadAsArray(buf_type=g.GDT_Float64)
    out[out <= nodata / 2] = np.nan      # FillNodata works in float32: unfilled cells read float32(-1e30)
    return out


def dtm_blocks(read: Callable[[slice, slice], np.ndarray], grid: Grid, search_cells: int,
               max_cells: int = BLOCK_CELLS,
               needed: Callable[[tuple[slice, slice]], bool] | None = None,
               reach_cells: float | None = None, pool: Executor | None = None,
               ahead: int = 1, plane_cells: int = 0) -> Iterator[tuple[Block, np.ndarray]]:
    """(block, DTM of its core): :func:`interpolate_dtm` of the ground heights ``read(rows, cols)``
    (float64, NaN: not ground), block by block, equal to the whole grid's.

    ``needed(core)``: False for a block nothing is drawn on (empty land in a sparse scene),
    which then stays NaN and costs nothing; default every block. ``reach_cells``: as in
    :func:`interpolate_dtm`; it also bounds how wide a block is read. ``pool``: forked workers
    (:func:`~pipeline25d.core.cores.fork_pool`) that fill the blocks, ``ahead`` at once, each
    reading its own window (``read`` must then pickle); the same values, in the same order.
    ``plane_cells``: as in :func:`interpolate_dtm`.

    A window reaches :func:`fill_reach` + 1 cells beyond its core, so the fill is exact on the
    core. A core cell it leaves empty takes its nearest filled cell, the whole grid's when that
    lies within the window's margin less that reach; where one does not (no ground that near), the block is
    read again with twice the margin. With ``reach_cells`` the first window sees that far.
    """
    from pipeline25d.core.cores import map_ahead

    blocks = dtm_layout(grid, search_cells, max_cells, plane_cells)
    wanted = [needed is None or needed(block.core) for block in blocks]
    filled = map_ahead(pool, block_dtm, ((read, grid, b.core, search_cells, reach_cells, plane_cells)
                                         for b, w in zip(blocks, wanted) if w), ahead)
    for block, w in zip(blocks, wanted):
        yield block, next(filled) if w else np.full(tuple(s.stop - s.start for s in block.core), np.nan)


def dtm_layout(grid: Grid, search_cells: int, max_cells: int = BLOCK_CELLS, plane_cells: int = 0) -> list[Block]:
    """The blocks :func:`dtm_blocks` fills: each core's window reaches :func:`fill_reach` + 1 cells beyond it
    (a mid-sized grid halved, so that two workers share it: the fill is exact either way)."""
    return cell_blocks(grid.height, grid.width, fill_reach(search_cells, plane_cells) + 1, max_cells, halve=True)


def block_dtm(read: Callable[[slice, slice], np.ndarray], grid: Grid, core: tuple[slice, slice], search_cells: int,
              reach_cells: float | None = None, plane_cells: int = 0) -> np.ndarray:
    """The DTM of one block's ``core`` (:func:`dtm_blocks`), from as wide a window as it needs."""
    reach = fill_reach(search_cells, plane_cells) + 1
    # with a reach, the first window already sees as far as any cell may take a value from
    margin = reach if reach_cells is None else reach + int(np.ceil(reach_cells)) + 1
    while (values := _dtm_core(read, grid, core, margin, search_cells, reach_cells, plane_cells)) is None:
        margin *= 2
    return values


def _dtm_core(read: Callable[[slice, slice], np.ndarray], grid: Grid, core: tuple[slice, slice], margin: int,
              search_cells: int, reach_cells: float | None = None, plane_cells: int = 0) -> np.ndarray | None:
    """The DTM of ``core`` from a window ``margin`` cells wider, or None if that is too narrow."""
    window = tuple(widen(s, margin, n) for s, n in zip(core, grid.shape))
    inner = Block(core, window).inner
    if all(w.start == 0 and w.stop == n for w, n in zip(window, grid.shape)):
        return interpolate_dtm(read(*window), search_cells, reach_cells, plane_cells)[inner]
    filled = _filled(read(*window), search_cells, plane_cells)
    values = filled[inner].copy()
    empty = ~np.isfinite(values)
    if not empty.any():
        return values
    # nearest filled cell among those the fill got exactly (its reach + 1 inside the window's cut sides)
    reach = fill_reach(search_cells, plane_cells) + 1
    exact = tuple(slice(0 if w.start == 0 else reach, (w.stop - w.start) - (0 if w.stop == n else reach))
                  for w, n in zip(window, grid.shape))
    source = np.full(filled.shape, np.nan)
    source[exact] = filled[exact]
    del filled
    # a nearest cell found within margin - reach is the whole grid's; one beyond reach_cells counts for none
    capped = reach_cells is not None and margin - reach > reach_cells
    if not np.isfinite(source).any():
        return np.full(values.shape, np.nan) if capped else None
    from scipy import ndimage as ndi

    if capped:          # a cell farther than reach_cells from every filled cell stays NaN: measure only near those
        nearest = np.full(source.shape, np.nan)
        for near, take in near_windows(np.isfinite(source), int(np.ceil(reach_cells)) + 1):
            dist, idx = ndi.distance_transform_edt(~np.isfinite(source[near]), return_indices=True)
            found = source[near][tuple(idx)]
            found[dist > reach_cells] = np.nan
            nearest[near][take] = found[take]
        values[empty] = nearest[inner][empty]
        return values
    dist, idx = ndi.distance_transform_edt(~np.isfinite(source), return_indices=True)
    if dist[inner][empty].max() > margin - reach:
        return None
    values[empty] = source[tuple(i[inner] for i in idx)][empty]
    return values
