"""A map kept between runs, with its overviews, and patched where its mosaic changed.

The map is made in fixed *blocks* of :data:`BLOCK_PX` x :data:`BLOCK_PX` pixels of its grid,
each on its own window, into a kept, tiled GeoTIFF: copied from the mosaic where no warp is
needed, else warped by GDAL with the chosen GCP warp. Each block's overviews are built from the
block alone; as a block holds whole pixels of every overview level, they are the map's. The
COG is then copied from that file, keeping its overviews. A later run hashes the mosaic in
squares of :data:`pipeline25d.core.raster.CELL_PX` pixels and redoes only the blocks that a
changed square reaches (through the warp: its outline mapped by the same GCP transformer,
grown by :data:`MARGIN_PX` for the bilinear kernel and gdalwarp's approximation). As every
block is always made on its own window, a patched map equals, byte for byte, one made from
scratch. A changed warp (method, order, GCPs), map grid or CRS redoes every block. The state
file journals the blocks being redone before the kept file is touched, so a killed run is
finished by the next one.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from collections.abc import Iterable, Iterator
from contextlib import contextmanager, nullcontext
from pathlib import Path

import numpy as np

from pipeline25d.core.cores import fork_pool, job_workers, map_ahead
from pipeline25d.core.geotiff import geotiff_dataset
from pipeline25d.core.grid import Grid, Window
from pipeline25d.core.journal import read_state, write_state
from pipeline25d.core.raster import cells_grid_of, gdal
from pipeline25d.stages.maps.mosaic_sources import source_windows
from pipeline25d.stages.maps.parts import box_outline

log = logging.getLogger(__name__)

BLOCK_PX = 2048        # a multiple of the COG's largest overview factor (2 ** 11 > any map's overview count)
MARGIN_PX = 2          # a changed mosaic square reaches this far (map px) beyond its warped outline
EDGE_SAMPLES = 9       # points per square edge sent through the warp (a polynomial bends the edge)
STATE_VERSION = 1
KEPT = "map.tif"


def warp_options(choice: dict, crs: str, gsd: float) -> dict:
    """gdal.Warp keywords of the chosen GCP warp onto the map grid (as gdalwarp -tap at ``gsd``);
    for no warp, a nearest-neighbour copy onto that grid."""
    opts = {"dstSRS": crs, "xRes": gsd, "yRes": gsd, "targetAlignedPixels": True, "dstAlpha": True,
            "resampleAlg": "near" if choice["method"] == "none" else "bilinear", "multithread": True,
            "warpOptions": ["NUM_THREADS=ALL_CPUS"]}
    if choice["method"] == "tps":
        opts["tps"] = True
    elif choice["method"] != "none":
        opts["polynomialOrder"] = choice["order"]
    return opts


def window_warp_options(choice: dict, crs: str, gsd: float) -> dict:
    """:func:`warp_options` for a window given by its own bounds (no -tap re-alignment)."""
    return {k: v for k, v in warp_options(choice, crs, gsd).items() if k != "targetAlignedPixels"}


def source_to_map(source: str | Path, choice: dict):
    """(x, y) in mosaic pixels -> (x, y) on the map, through GDAL's GCP transformer of ``source``."""

    g = gdal()
    transformer = g.Transformer(g.Open(str(source)), None, transformer_options(choice["method"], choice["order"]))

    def to_map(col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xy, _ = transformer.TransformPoints(0, np.column_stack([col, row, np.zeros(len(col))]).tolist())
        xy = np.asarray(xy, dtype=np.float64)
        return xy[:, 0], xy[:, 1]

    return to_map


def patched_map(mosaic: str | Path, source: str | Path, choice: dict, crs: str, gsd: float,
                work: Path, cells_memo: dict | None = None, threads: int = 1) -> tuple[Path, dict]:
    """Bring the map kept in ``work`` up to the ``mosaic``: copied where ``choice`` is no warp,
    else warped from ``source`` (a VRT of the mosaic with its GCPs). Returns the kept GeoTIFF,
    with its overviews, and the run's figures (full or not, squares changed, blocks redone) with
    ``map_cells``: the kept map's own digests (:func:`~pipeline25d.core.raster.map_cells`), taken
    from the blocks as they are written (None where an older state has none for the blocks kept).
    ``threads``: the job's threads; the blocks are made by that many worker processes, or by as
    many as there are cores idle when it starts (:func:`~pipeline25d.core.cores.job_workers`: the
    last map of a run, alone), one block ahead, and written here in order (the same bytes whatever
    the count). The kept file is flushed after each block (:func:`write_block`, :func:`write_levels`):
    its written blocks then leave GDAL's block cache (capped, :data:`~pipeline25d.core.raster.CACHE_MB`)
    as the next block's arrive, rather than being pushed out of it by them (a make bench map, made here: 20.2 s and
    23.1 CPU-s without the flush, 13.8 s and 16.8 CPU-s with it, 13.7 and 16.9 with no flush and
    a 1 GB cache; by two workers 11.6 s, 20.2 CPU-s; one run each, back to back)."""
    from pipeline25d.core.raster import CELL_PX, cells_grid, map_cells
    from pipeline25d.stages.maps.parts import overview_factors

    g = gdal()
    warped = choice["method"] != "none"
    target = g.Warp("", str(source), format="VRT", **warp_options(choice, crs, gsd)) if warped else g.Open(str(mosaic))
    grid, bands = Grid.of_dataset(target), target.RasterCount
    width, height = grid.width, grid.height
    target = None
    factors = overview_factors(width, height)
    size = max(BLOCK_PX, factors[-1] if factors else 1)      # a block holds whole pixels of every overview
    key = {"version": STATE_VERSION, "method": choice["method"], "order": choice.get("order"), "crs": crs,
           "gcps": gcps_digest(source) if warped else None, "grid": [*grid.geotransform, width, height], "block": size,
           "overviews": factors}
    mosaic_grid = cells_grid(Grid.of_dataset(g.Open(str(mosaic))))
    key["mosaic"] = mosaic_grid
    state = read_state(work)
    full = state is None or state["key"] != key or not (work / KEPT).is_file()
    # a copied map is its mosaic pixel for pixel: made whole, the blocks give the mosaic's digests as they go
    cells = None if full and not warped else map_cells(mosaic, memo=cells_memo)[1]
    nx, ny = -(-width // size), -(-height // size)
    if full:
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        # a block that no square of the mosaic holding data reaches holds nothing: not made, and a
        # new kept file leaves it unwritten (read as zeros)
        held = list(cells) if warped else cells_under(source_windows(mosaic, mosaic_grid), mosaic_grid[8])
        to_map = source_to_map(source, choice) if warped else pixel_to_map(mosaic_grid)
        todo = blocks_reached(held, mosaic_grid, to_map, grid, size, MARGIN_PX if warped else 0)
        changed: list[str] = []
    else:
        old = state["cells"]
        changed = sorted(c for c in cells.keys() | old.keys() if cells.get(c) != old.get(c))
        to_map = source_to_map(source, choice) if warped else pixel_to_map(mosaic_grid)
        todo = {tuple(b) for b in state["dirty"]} | blocks_reached(changed, mosaic_grid, to_map, grid, size,
                                                                   MARGIN_PX if warped else 0)
    todo = sorted(todo)
    own = {} if full else state.get("map_cells")            # the kept map's digests, block by block
    write_state(work, {"key": key, "cells": {} if full else state["cells"], "dirty": todo})    # journal first
    wins = [block_window(bx, by, width, height, size) for bx, by in todo]
    workers = job_workers(threads) if len(wins) > 1 else 1
    opts = {k: v for k, v in window_warp_options(choice, crs, gsd).items() if k not in ("xRes", "yRes")}
    if workers > 1:      # a forked worker has no GDAL thread pool (its threads stay in this process): one thread
        opts = {k: v for k, v in opts.items() if k not in ("multithread", "warpOptions")}
    made = ((str(source) if warped else str(mosaic), opts if warped else None, grid.window_bounds(win), win, factors,
             own is not None, full) for win in wins)
    # the workers are forked before the kept file is opened: none of them holds it
    with fork_pool(workers) if workers > 1 else nullcontext() as pool, \
            kept_dataset(work / KEPT, full, grid, crs, factors, bands=bands) as kept:
        if pool is None:                    # here: the block's levels go straight from its overview file
            for source_path, warp, bounds, win, *_ in made:
                block = make_block(source_path, warp, bounds, win)
                if not (full and blank(block)):
                    write_block(kept, block, win, factors)
                if own is not None:
                    _redigest(own, block_digests(block, win), win, CELL_PX)
        else:                               # by the workers, one block ahead of the writes here
            for win, (levels, digests) in zip(wins, map_ahead(pool, block_levels, made, workers + 1)):
                if levels is not None:
                    write_levels(kept, levels, win, factors)
                if own is not None:
                    _redigest(own, digests, win, CELL_PX)
    if cells is None:
        cells = own
        if cells_memo is not None:
            cells_memo[(str(mosaic), CELL_PX)] = (mosaic_grid, cells)
    write_state(work, {"key": key, "cells": cells, "dirty": [], "map_cells": own})
    stats = {"full": full, "mosaic_cells_changed": len(changed), "blocks_redone": len(todo), "blocks": nx * ny,
             "map_cells": None if own is None else (cells_grid(grid), own)}
    log.info("map: %s; %d mosaic squares changed, %d of %d map blocks %s", "full" if full else "patch",
             len(changed), len(todo), nx * ny, "warped" if warped else "copied")
    return work / KEPT, stats


def block_levels(source: str, warp: dict | None, bounds: tuple[float, float, float, float], win: Window,
                 factors: list[int], digest: bool, skip_blank: bool = False
                 ) -> tuple[list[list[tuple[int, int, bytes]]] | None, dict[str, str] | None]:
    """One block of the map, made on its own window: warped from ``source`` with the gdal.Warp
    keywords ``warp``, or copied from it (None); returns each band's pixels and overview levels
    (:func:`write_levels`; None for a :func:`blank` block where ``skip_blank``: a new kept file
    holds its zeros unwritten) and, with ``digest``, its squares' digests. Runs in a worker
    process where the job has idle cores: it opens everything it reads."""
    block = make_block(source, warp, bounds, win)
    levels = None if skip_blank and blank(block) else block_overviews(block, factors, _read_levels)
    return levels, block_digests(block, win) if digest else None


def blank(block) -> bool:
    """Whether every pixel of every band of the in-memory ``block`` is 0 (transparent, nothing drawn):
    a block of a new kept file that is never written (its file is sparse: GDAL reads such a block
    as zeros, at every overview level). A sparse city's map (Zurich's 210 buildings over 9 x 10 km
    at 0.5 m): 90 blocks, 57 of them blank, made in 4.7 s instead of 10.8 s (one run)."""
    return not np.frombuffer(block.ReadRaster(), dtype=np.uint8).any()


def block_digests(block, win: Window) -> dict[str, str]:
    """The digests of the squares of map window ``win`` that the in-memory ``block`` fills."""
    from pipeline25d.core.raster import CELL_PX, window_cells

    return window_cells(block, Window(0, 0, win.width, win.height), CELL_PX, at=(win.col0, win.row0))


def make_block(source: str, warp: dict | None, bounds: tuple[float, float, float, float], win: Window):
    """The in-memory block of map window ``win``: warped from ``source`` with the gdal.Warp keywords
    ``warp`` onto ``bounds``, or copied from it (None)."""
    g = gdal()
    if warp is not None:
        return g.Warp("", source, format="MEM", outputBounds=bounds, width=win.width, height=win.height, **warp)
    return g.Translate("", source, format="MEM", srcWin=[win.col0, win.row0, win.width, win.height])


def _redigest(digests: dict[str, str], new: dict[str, str], win: Window, cell: int) -> None:
    """Replace the digests of the squares of map window ``win`` by ``new``, those of its new pixels."""
    for square in cells_under([win], cell):
        digests.pop(square, None)
    digests.update(new)


def write_block(kept, block, win: Window, factors: list[int], resampling: str = "AVERAGE") -> None:
    """A block's pixels and its own overviews (its footprint holds whole overview pixels, so they
    are the map's) into the kept GeoTIFF. The overviews are built by the GeoTIFF driver, all bands
    at once with the alpha as their mask, as for a sparse map's parts (the in-memory driver's
    per-band path weights partly transparent pixels otherwise); ``resampling``: GDAL's overview
    method (NEAREST for object ids). Each level is written as it is read, band by band; then the
    block is flushed (see :func:`write_levels`)."""
    block_overviews(block, factors, lambda ds: write_levels(kept, _levels(ds), win, factors), resampling)


def block_overviews(block, factors: list[int], use, resampling: str = "AVERAGE"):
    """``use(dataset)`` on ``block`` with its overviews built (see :func:`write_block`)."""
    if not factors:
        return use(block)
    path = f"/vsimem/map_patch_{os.getpid()}_{id(block)}.tif"
    block = gdal().GetDriverByName("GTiff").CreateCopy(path, block)
    try:
        block.BuildOverviews(resampling, factors)
        return use(block)
    finally:
        block = None
        gdal().Unlink(path)


def _levels(block) -> Iterator[Iterator[tuple[int, int, bytes]]]:
    """Each band's (width, height, pixels), then its overviews', finest first: each read when it
    is drawn, so that :func:`write_levels` writes a block's levels one at a time."""
    for b in range(1, block.RasterCount + 1):
        band = block.GetRasterBand(b)
        yield ((o.XSize, o.YSize, o.ReadRaster())
               for o in (band, *(band.GetOverview(k) for k in range(band.GetOverviewCount()))))


def _read_levels(block) -> list[list[tuple[int, int, bytes]]]:
    """:func:`_levels` read whole: the bytes a worker hands back."""
    return [list(band) for band in _levels(block)]


def write_levels(kept, levels: Iterable[Iterable[tuple[int, int, bytes]]], win: Window, factors: list[int]) -> None:
    """A block's levels (:func:`_levels`, :func:`_read_levels`) into the kept GeoTIFF at map
    window ``win``, then flushed: the written block leaves GDAL's capped cache now rather than
    being pushed out of it by the next block's (see :func:`patched_map`)."""
    for b, band_levels in enumerate(levels, start=1):
        dst = kept.GetRasterBand(b)
        targets = (dst, *(dst.GetOverview(k) for k in range(len(factors))))
        for target, f, (w, h, pixels) in zip(targets, (1, *factors), band_levels, strict=True):
            target.WriteRaster(win.col0 // f, win.row0 // f, w, h, pixels)
    kept.FlushCache()


def gcps_digest(source: str | Path) -> str:
    src = gdal().Open(str(source))
    gcps = [(p.GCPPixel, p.GCPLine, p.GCPX, p.GCPY, p.GCPZ) for p in src.GetGCPs()]
    return hashlib.sha256(json.dumps(gcps).encode()).hexdigest()[:16]


def pixel_to_map(mosaic_grid: list):
    return cells_grid_of(mosaic_grid).xy


def cells_under(windows: Iterable[tuple[int, int, int, int]], cell: int) -> list[str]:
    """The squares (``col_row``) of ``cell`` px (:func:`~pipeline25d.core.raster.map_cells`') that
    pixel windows (col0, row0, col1, row1) meet."""
    out: set[str] = set()
    for c0, r0, c1, r1 in windows:
        if c1 > c0 and r1 > r0:
            out |= {f"{c}_{r}" for c in range(c0 // cell, (c1 - 1) // cell + 1)
                    for r in range(r0 // cell, (r1 - 1) // cell + 1)}
    return sorted(out)


def block_window(bx: int, by: int, width: int, height: int, size: int) -> Window:
    """The pixel window of block (bx, by), ``size`` px square, of a map ``width`` x ``height``."""
    return Window(bx * size, by * size, min((bx + 1) * size, width), min((by + 1) * size, height))


def blocks_reached(cell_ids: list[str], mosaic_grid: list, to_map, grid: Grid, size: int,
                   margin: int) -> set[tuple[int, int]]:
    """The map blocks (``size`` px) that mosaic squares ``cell_ids`` (of
    :func:`pipeline25d.core.raster.map_cells`) reach through ``to_map`` (mosaic pixels -> map
    x, y), grown by ``margin`` px."""
    if not cell_ids:
        return set()
    cell, mw, mh, width, height = mosaic_grid[8], mosaic_grid[6], mosaic_grid[7], grid.width, grid.height
    ids = np.array([[int(v) for v in c.split("_")] for c in cell_ids])
    c0, r0 = ids[:, 0] * cell, ids[:, 1] * cell
    c1, r1 = np.minimum(c0 + cell, mw), np.minimum(r0 + cell, mh)
    outlines = [box_outline(*b, n=EDGE_SAMPLES) for b in zip(c0, r0, c1, r1)]
    x, y = to_map(np.concatenate([o[0] for o in outlines]), np.concatenate([o[1] for o in outlines]))
    col, row = (v.reshape(len(cell_ids), -1) for v in grid.colrow(x, y))
    out = set()
    for a0, a1, b0, b1 in zip(col.min(axis=1), col.max(axis=1), row.min(axis=1), row.max(axis=1)):
        # the pixels [a0, a1) x [b0, b1) the square's outline spans (grown by the margin)
        a0, b0 = max(int(np.floor(a0 + 1e-9)) - margin, 0), max(int(np.floor(b0 + 1e-9)) - margin, 0)
        a1, b1 = min(int(np.ceil(a1 - 1e-9)) + margin, width), min(int(np.ceil(b1 - 1e-9)) + margin, height)
        if a1 > a0 and b1 > b0:
            out |= {(bx, by) for bx in range(a0 // size, (a1 - 1) // size + 1)
                    for by in range(b0 // size, (b1 - 1) // size + 1)}
    return out


KEPT_OPTIONS = ["TILED=YES", "BLOCKXSIZE=512", "BLOCKYSIZE=512", "COMPRESS=ZSTD", "ZSTD_LEVEL=1", "SPARSE_OK=TRUE",
                "BIGTIFF=IF_SAFER"]


@contextmanager
def kept_dataset(path: Path, new: bool, grid: Grid, crs: str, factors: list[int], bands: int = 4,
                 dtype: str = "Byte", options: list[str] | None = None, nodata: float | None = None) -> Iterator:
    """The kept GeoTIFF open for writing blocks: made anew with empty overview levels (it appears
    at ``path`` when the ``with`` ends) or, not ``new``, opened for update. A new file is written
    through the handle that made it: GDAL keeps ``ZSTD_LEVEL`` only there, and a file opened for
    update compresses at zstd's default level 9, five times slower (1.0 against 0.2 CPU-s for
    a 44 MB map); the few blocks a patch rewrites pay that, a whole map does not."""
    if not new:
        ds = gdal().Open(str(path), 1)
        try:
            yield ds
            ds.FlushCache()
        finally:
            ds = None
        return
    if options is None:          # a map's colours and alpha
        options = [*KEPT_OPTIONS, "INTERLEAVE=BAND", *(["PHOTOMETRIC=RGB"] if bands >= 4 else []), "ALPHA=YES"]
    with geotiff_dataset(path, grid, crs, bands, dtype, options, nodata=nodata, overviews=factors) as out:
        yield out.ds


def transformer_options(method: str, order: int) -> list[str]:
    """GDAL GCP transformer options of a warp method (tps, or polynomial of ``order``)."""
    return ["METHOD=GCP_TPS"] if method == "tps" else ["METHOD=GCP_POLYNOMIAL", f"MAX_GCP_ORDER={order}"]
