"""A north-up grid of square cells, blocks of its cells, and its float32 GeoTIFFs (read, written block by block)."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from pipeline25d.core.atomic import atomic_path
from pipeline25d.core.raster import gdal

log = logging.getLogger(__name__)


TIFF_TILE = 256             # GeoTIFF tile edge (GDAL's default); block cores are cut at its multiples


# Cells of a block's window (core and margins). The CSF holds ~115 bytes a cell (cloth particles
# of 2 x 2 cells, its copy of the points), the trimming ~40: ~0.5 GB a block at most (measured
# 0.36 GB on Delft's LiDAR mesh, whose CSF blocks are 2.7 M cells at 0.5 m).
BLOCK_CELLS = 1 << 22


@dataclass(frozen=True)
class Grid:
    """A north-up raster grid: top-left corner (xmin, ymax), square cells of ``res`` metres."""

    xmin: float
    ymax: float
    res: float
    width: int
    height: int

    @classmethod
    def covering(cls, bounds_xy: tuple[float, float, float, float], res: float) -> "Grid":
        """The grid of ``res`` cells aligned to multiples of ``res`` that covers the bounds."""
        xmin, ymin, xmax, ymax = bounds_xy
        x0, y0 = math.floor(xmin / res) * res, math.floor(ymin / res) * res
        x1, y1 = math.ceil(xmax / res) * res, math.ceil(ymax / res) * res
        return cls(x0, y1, res, max(1, round((x1 - x0) / res)), max(1, round((y1 - y0) / res)))

    @property
    def geotransform(self) -> tuple[float, ...]:
        return (self.xmin, self.res, 0.0, self.ymax, 0.0, -self.res)

    @property
    def bounds_xy(self) -> tuple[float, float, float, float]:
        return (self.xmin, self.ymax - self.height * self.res, self.xmin + self.width * self.res, self.ymax)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    def column_x(self) -> np.ndarray:
        """(width,) float64 x of the cell centres of each column."""
        return self.xmin + (np.arange(self.width) + 0.5) * self.res

    def row_y(self) -> np.ndarray:
        """(height,) float64 y of the cell centres of each row (row 0 is north)."""
        return self.ymax - (np.arange(self.height) + 0.5) * self.res

    def cell_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(height, width) float64 x and y of every cell centre."""
        return np.meshgrid(self.column_x(), self.row_y())

    def window(self, rows: slice, cols: slice) -> "Grid":
        """The grid of the cells ``rows`` x ``cols`` (half-open slices within this grid)."""
        return Grid(self.xmin + cols.start * self.res, self.ymax - rows.start * self.res, self.res,
                    cols.stop - cols.start, rows.stop - rows.start)


class Block(NamedTuple):
    """A core of cells and the window read around it: (rows, cols) half-open slices of the grid."""

    core: tuple[slice, slice]
    window: tuple[slice, slice]

    @property
    def inner(self) -> tuple[slice, slice]:
        """The core's cells within the window."""
        return tuple(slice(c.start - w.start, c.stop - w.start) for c, w in zip(self.core, self.window))


def cell_blocks(height: int, width: int, margin: int, max_cells: int = BLOCK_CELLS,
                row_cuts: Sequence[int] | None = None, col_cuts: Sequence[int] | None = None,
                align: int = 1) -> list[Block]:
    """Cores tiling a height x width grid, each with a window ``margin`` cells wider on every side.

    A grid of at most ``max_cells`` cells is one block (so small scenes are processed whole).
    Otherwise each axis is cut into about equal spans so that a window is about
    sqrt(max_cells) cells wide; cuts fall only at ``row_cuts``/``col_cuts`` (default: multiples
    of TIFF_TILE, so each block written fills whole GeoTIFF tiles). ``align``: windows start
    (columns) and end (rows, counted from the grid's bottom row) at multiples of it, which keeps
    the CSF's cloth grid, anchored at the lower-left point, where the whole grid has it.
    """
    if height * width <= max_cells:
        whole = (slice(0, height), slice(0, width))
        return [Block(whole, whole)]
    span = max(math.isqrt(max_cells) - 2 * margin, margin, TIFF_TILE)
    blocks = []
    for r0, r1 in _spans(height, span, row_cuts):
        for c0, c1 in _spans(width, span, col_cuts):
            c_start = max(c0 - margin, 0)
            r_stop = min(r1 + margin, height)
            window = (slice(max(r0 - margin, 0), r_stop + (height - r_stop) % align),
                      slice(c_start - c_start % align, min(c1 + margin, width)))
            blocks.append(Block((slice(r0, r1), slice(c0, c1)), window))
    return blocks


def _spans(length: int, span: int, cuts: Sequence[int] | None) -> list[tuple[int, int]]:
    """About equal (start, stop) spans of about ``span`` cells covering 0..length, cut only at ``cuts``."""
    allowed = np.arange(TIFF_TILE, length, TIFF_TILE) if cuts is None else np.asarray(cuts, dtype=np.int64)
    allowed = allowed[(allowed > 0) & (allowed < length)]
    n = math.ceil(length / span)
    if n < 2 or not len(allowed):
        return [(0, length)]
    ideal = np.arange(1, n) * length / n
    chosen = allowed[np.abs(allowed[:, None] - ideal[None]).argmin(axis=0)]
    edges = np.unique(np.r_[0, chosen, length])
    return list(zip(edges[:-1].tolist(), edges[1:].tolist()))


def widen(s: slice, by: int, length: int) -> slice:
    return slice(max(s.start - by, 0), min(s.stop + by, length))


class FloatRaster:
    """A one-band float GeoTIFF read by windows, memory O(window)."""

    def __init__(self, path: str | Path):
        self._ds = gdal().Open(str(path))
        gt = self._ds.GetGeoTransform()
        self.grid = Grid(gt[0], gt[3], gt[1], self._ds.RasterXSize, self._ds.RasterYSize)

    def read(self, rows: slice, cols: slice, dtype: type = np.float64) -> np.ndarray:
        """The cells ``rows`` x ``cols`` (NaN nodata); GDAL's cached blocks are dropped after."""
        g = gdal()
        band = self._ds.GetRasterBand(1)
        buf = g.GDT_Float32 if np.dtype(dtype) == np.float32 else g.GDT_Float64
        values = band.ReadAsArray(cols.start, rows.start, cols.stop - cols.start, rows.stop - rows.start,
                                  buf_type=buf)
        band.FlushCache()
        return values

    def read_all(self, dtype: type = np.float64) -> np.ndarray:
        return self.read(slice(0, self.grid.height), slice(0, self.grid.width), dtype)


@contextmanager
def float_geotiff_writer(path: str | Path, grid: Grid, wkt: str) -> Iterator[Callable[[np.ndarray, int, int], None]]:
    """``write(values, row, col)`` puts an (h, w) block of heights at (row, col) of a tiled, deflated
    float32 GeoTIFF (NaN nodata) that appears at ``path`` when the ``with`` ends without error.

    Float32 keeps heights to ~1e-5 m at 100 m, finer than the nadir render's depth steps.
    A written block leaves GDAL's cache at once (memory O(block)); blocks covering whole
    TIFF_TILE tiles write each tile once. All-NaN blocks are not written: the file is sparse
    (GDAL reads unwritten tiles as nodata), so empty land costs neither time nor disk.
    """
    g = gdal()
    with atomic_path(path) as tmp:
        ds = g.GetDriverByName("GTiff").Create(str(tmp), grid.width, grid.height, 1, g.GDT_Float32,
                                               ["COMPRESS=DEFLATE", "PREDICTOR=3", "TILED=YES", "SPARSE_OK=TRUE",
                                                f"BLOCKXSIZE={TIFF_TILE}", f"BLOCKYSIZE={TIFF_TILE}"])
        ds.SetGeoTransform(grid.geotransform)
        ds.SetProjection(wkt)
        band = ds.GetRasterBand(1)
        band.SetNoDataValue(float("nan"))

        def write(values: np.ndarray, row: int, col: int) -> None:
            if not np.isfinite(values).any():
                return
            band.WriteArray(values.astype(np.float32, copy=False), col, row)
            band.FlushCache()

        try:
            yield write
            ds.FlushCache()
        finally:
            band = ds = None


def write_float_geotiff(path: str | Path, values: np.ndarray, grid: Grid, wkt: str) -> None:
    """An (h, w) float raster as a tiled, deflated float32 GeoTIFF (NaN nodata), atomically."""
    with float_geotiff_writer(path, grid, wkt) as write:
        for row in range(0, grid.height, TIFF_TILE):     # a row of tiles at a time
            write(values[row:row + TIFF_TILE], row, 0)


def read_float_geotiff(path: str | Path) -> tuple[np.ndarray, Grid]:
    """Inverse of :func:`write_float_geotiff` (float64 values, NaN nodata)."""
    raster = FloatRaster(path)
    return raster.read_all(), raster.grid
