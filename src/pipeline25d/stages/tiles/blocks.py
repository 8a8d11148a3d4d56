"""The web-mercator blocks a map is cut from: warped by gdalwarp onto the tile grid and kept.

A block is warped on the map's web-mercator grid (:func:`~.web.tile_grid`: the tiles' pixels,
halved until no coarser than the map's) with the nearest-neighbour resampling of gdal2tiles'
own warp. Where that grid is finer than the tiles' (2 or 4 of its pixels a side to a tile
pixel: :data:`STORED_FACTORS`), the block is kept as the average that gdal2tiles' base tile
would take of it (:func:`box_mean`, its rounding) on the tiles' own pixels: a quarter (or a
sixteenth) of the pixels to compress, keep and read again, and the same tiles byte for byte.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import atomic_path
from pipeline25d.core.grid import Extent, Grid, Window
from pipeline25d.core.raster import gdal, stores_nothing
from pipeline25d.stages.tiles.base import box_sums

WEB_MERCATOR = "EPSG:3857"
GDAL2TILES_TILE = 256
STORED_FACTORS = (2, 4)   # warp pixels a side to a tile pixel that a block is averaged by before it is kept
BLOCK_OPTIONS = ["TILED=YES", "COMPRESS=ZSTD", "ZSTD_LEVEL=1"]
SOURCE_MARGIN_PX = 2       # map pixels a block's outline is grown by when asking whether the map stores any there
SOURCE_EDGE_SAMPLES = 9    # points per block edge taken to the map's CRS


def tile_metres(max_zoom: int) -> tuple[float, float]:
    """(origin, tile): the web-tile grid starts at (-origin, -origin); a tile of ``max_zoom`` is tile m wide."""
    from osgeo_utils.gdal2tiles import GlobalMercator

    origin = GlobalMercator(GDAL2TILES_TILE).originShift
    return origin, 2 * origin / 2 ** max_zoom


def stored_factor(grid: Grid, max_zoom: int) -> int:
    """The warp grid's pixels a side to a tile pixel of ``max_zoom`` that a block is averaged by
    before it is kept: 2 or 4 (:data:`STORED_FACTORS`), else 1 (kept as warped: an id raster's grid,
    which is the tiles', or a map's grid more than 4 times finer, whose base tiles gdal2tiles reads
    through a query coarser than the window, not by averaging all of it)."""
    _, tile = tile_metres(max_zoom)
    factor = round(tile / GDAL2TILES_TILE / grid.transform.a)
    return factor if factor in STORED_FACTORS else 1


def stored_grid(grid: Grid, factor: int) -> Grid:
    """The grid the blocks are kept on: ``grid`` with pixels ``factor`` times as wide (its edges are
    the tiles' edges, so the sizes divide)."""
    if factor == 1:
        return grid
    x0, _, _, y1 = grid.bounds
    return Grid.north_up(x0, y1, grid.transform.a * factor, grid.width // factor, grid.height // factor)


def box_mean(bands: np.ndarray, factor: int) -> np.ndarray:
    """(b, h/f, w/f) uint8: each band's mean over ``factor`` x ``factor`` pixels, rounded half up as
    gdal2tiles' average of a base tile's query rounds it (:func:`~.base.average_tile`: a window f
    times finer than the tile is each of its pixels repeated 4/f times in the 4x query, whose 4 x 4
    sums are then (16/f² · S + 8) // 16 = (S + f²/2) // f²)."""
    return ((box_sums(bands, factor) + factor * factor // 2) // (factor * factor)).astype(np.uint8)


def warp_block(cog: str, blocks_dir: str, grid: Grid, ids: bool, factor: int,
               job: tuple[tuple[int, int], Window]) -> None:
    """Warp the map (``ids``: its id raster) onto one block's window of its web-mercator grid and
    keep it, averaged by ``factor`` (:func:`stored_factor`), written atomically."""
    block, window = job
    bounds = grid.window_bounds(Window(*window))
    extra = ["-tr", repr(grid.transform.a), repr(-grid.transform.e), "-te", *map(repr, bounds)]
    g = gdal()
    with atomic_path(Path(blocks_dir) / f"{block[0]}_{block[1]}.tif") as tmp:
        if factor == 1:
            options = mercator_args(1, extra, alpha=not ids) + [a for o in BLOCK_OPTIONS for a in ("-co", o)]
            g.Warp(str(tmp), cog, options=options)
            return
        warped = g.Warp("", cog, options=["-of", "MEM", *mercator_args(1, extra)])
        kept = g.GetDriverByName("MEM").Create("", warped.RasterXSize // factor, warped.RasterYSize // factor,
                                               warped.RasterCount)
        x0, res, _, y1, _, _ = warped.GetGeoTransform()
        kept.SetGeoTransform((x0, res * factor, 0.0, y1, 0.0, -res * factor))
        kept.SetProjection(warped.GetProjection())
        kept.WriteRaster(0, 0, kept.RasterXSize, kept.RasterYSize, box_mean(warped.ReadAsArray(), factor).tobytes())
        for i in range(1, warped.RasterCount + 1):
            kept.GetRasterBand(i).SetColorInterpretation(warped.GetRasterBand(i).GetColorInterpretation())
        g.GetDriverByName("GTiff").CreateCopy(str(tmp), kept, options=BLOCK_OPTIONS)


def over_nothing(cog: str, grid: Grid, jobs: list[tuple[tuple[int, int], Window]],
                 margin: int = SOURCE_MARGIN_PX) -> set[tuple[int, int]]:
    """The blocks of ``jobs`` (block, window on the web-mercator ``grid``) under which the map
    ``cog`` stores no pixel: each window's outline taken to the map's CRS, grown by ``margin`` map
    pixels (gdalwarp's nearest pixel, its 0.01 px approximation), meets only blocks the map never
    stored (a sparse COG's, which GDAL reads as zeros: its data coverage EMPTY) or lies off the
    map. A map that stores every block (GDAL: no EMPTY anywhere) is not asked block by block.
    Zurich's 210 buildings over 9 x 10 km: 1,350 of a map's 1,404 blocks of 512 px are unstored."""
    from pipeline25d.core.crs import transform_points
    from pipeline25d.stages.maps.parts import box_outline

    ds = gdal().Open(cog)
    band, empty = ds.GetRasterBand(1), gdal().GDAL_DATA_COVERAGE_STATUS_EMPTY
    if not jobs or not band.GetDataCoverageStatus(0, 0, ds.RasterXSize, ds.RasterYSize)[0] & empty:
        return set()
    outlines = [box_outline(*grid.window_bounds(Window(*w)), n=SOURCE_EDGE_SAMPLES) for _, w in jobs]
    xs, ys = np.concatenate([o[0] for o in outlines]), np.concatenate([o[1] for o in outlines])
    xy = transform_points(np.column_stack([xs, ys, np.zeros(len(xs))]), WEB_MERCATOR, ds.GetProjection())
    xy = xy[:, :2].reshape(len(jobs), -1, 2)
    lo, hi, map_grid = xy.min(axis=1), xy.max(axis=1), Grid.of_dataset(ds)
    out = set()
    for (block, _), (x0, y0), (x1, y1) in zip(jobs, lo, hi):
        w = map_grid.window_covering(Extent(x0, y0, x1, y1), margin).clipped(map_grid.width, map_grid.height)
        if w.col1 <= w.col0 or w.row1 <= w.row0 or stores_nothing(band, w):
            out.add(block)
    return out


def mercator_args(threads: int, extra: list[str] | None = None, alpha: bool = True) -> list[str]:
    """gdalwarp's arguments; ``alpha`` False (an id raster): its nodata 0 kept instead of an alpha band."""
    return ["-q", "-overwrite", "-t_srs", WEB_MERCATOR, "-r", "near", "-et", "0.01",
            *(["-dstalpha"] if alpha else ["-srcnodata", "0", "-dstnodata", "0"]), "-multi",
            "-wo", f"NUM_THREADS={threads}", *(extra or [])]
