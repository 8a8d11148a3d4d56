"""The raster layer's geometry: a grid of cells placed by an affine transform (``affine``, as in
rasterio), a pixel window on it, a world rectangle, and blocks of a grid's cells.

Pixel <-> world conversions of the whole project go through :class:`Grid`: world = transform @
(col, row) (pixel corners; cell centres at +0.5). World -> pixel of a north-up grid divides by
the cell size, ``(x - c) / a``, which is the exact inverse; ``~transform`` (``x / a - c / a``)
rounds differently and would move floor/ceil at cell edges, so it is used only for rotated grids.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from affine import Affine

TIFF_TILE = 256             # GeoTIFF tile edge (GDAL's default); block cores are cut at its multiples
HALVE_SPANS = 4             # cell_blocks(halve=True): a one-block grid this many margins long is cut in two


# Cells of a block's window (core and margins). The CSF holds ~115 bytes a cell (cloth particles
# of 2 x 2 cells, its copy of the points), the trimming ~40: ~0.5 GB a block at most (measured
# 0.36 GB on Delft's LiDAR mesh, whose CSF blocks are 2.7 M cells at 0.5 m).
BLOCK_CELLS = 1 << 22


class Extent(NamedTuple):
    """Axis-aligned world rectangle in CRS units (metres): the one type of bounds that travels."""

    xmin: float
    ymin: float
    xmax: float
    ymax: float

    @property
    def width(self) -> float:
        return self.xmax - self.xmin

    @property
    def height(self) -> float:
        return self.ymax - self.ymin


class Window(NamedTuple):
    """A pixel rectangle of a grid: columns col0..col1, rows row0..row1 (end exclusive)."""

    col0: int
    row0: int
    col1: int
    row1: int

    @property
    def width(self) -> int:
        return self.col1 - self.col0

    @property
    def height(self) -> int:
        return self.row1 - self.row0

    @property
    def slices(self) -> tuple[slice, slice]:
        """(rows, cols) half-open slices, for numpy indexing and :meth:`Grid.window`."""
        return slice(self.row0, self.row1), slice(self.col0, self.col1)

    @classmethod
    def of_slices(cls, rows: slice, cols: slice) -> "Window":
        return cls(cols.start, rows.start, cols.stop, rows.stop)

    def clipped(self, width: int, height: int) -> "Window":
        """This window cut to a ``width`` x ``height`` grid (empty, col1 <= col0 or row1 <= row0, off it)."""
        return Window(max(self.col0, 0), max(self.row0, 0), min(self.col1, width), min(self.row1, height))

    def scaled_down(self, factor: int) -> "Window":
        """The window of a grid with pixels ``factor`` times as wide that covers this one."""
        if factor == 1:
            return self
        return Window(self.col0 // factor, self.row0 // factor, -(-self.col1 // factor), -(-self.row1 // factor))


@dataclass(frozen=True)
class Grid:
    """``width`` x ``height`` cells placed by ``transform`` (world = transform @ (col, row)).

    Usually north-up with square cells (``north_up``): then ``xmin``/``ymax`` are its top-left
    corner and ``res`` its cell size.
    """

    transform: Affine
    width: int
    height: int

    @classmethod
    def north_up(cls, xmin: float, ymax: float, res: float, width: int, height: int) -> "Grid":
        """The grid whose top-left corner is (xmin, ymax), of square cells of ``res``."""
        return cls(Affine(float(res), 0.0, float(xmin), 0.0, -float(res), float(ymax)), int(width), int(height))

    @classmethod
    def of_dataset(cls, ds: Any) -> "Grid":
        """The grid of a GDAL dataset (its geotransform and size)."""
        return cls(Affine.from_gdal(*ds.GetGeoTransform()), ds.RasterXSize, ds.RasterYSize)

    @classmethod
    def from_gdal(cls, geotransform: Sequence[float], width: int, height: int) -> "Grid":
        """The grid of GDAL's six geotransform numbers (for records that store them)."""
        return cls(Affine.from_gdal(*geotransform), int(width), int(height))

    @classmethod
    def covering(cls, bounds: Sequence[float], res: float) -> "Grid":
        """The grid of ``res`` cells aligned to multiples of ``res`` that covers (xmin, ymin, xmax, ymax)."""
        xmin, ymin, xmax, ymax = bounds
        x0, y0 = math.floor(xmin / res) * res, math.floor(ymin / res) * res
        x1, y1 = math.ceil(xmax / res) * res, math.ceil(ymax / res) * res
        return cls.north_up(x0, y1, res, max(1, round((x1 - x0) / res)), max(1, round((y1 - y0) / res)))

    @property
    def geotransform(self) -> tuple[float, float, float, float, float, float]:
        """GDAL's order (c, a, b, f, d, e), for SetGeoTransform and the records that store it."""
        return self.transform.to_gdal()

    @property
    def xmin(self) -> float:
        return self.transform.c

    @property
    def ymax(self) -> float:
        return self.transform.f

    @property
    def res(self) -> float:
        """The cell width (a north-up grid's cell size)."""
        return self.transform.a

    @property
    def is_north_up(self) -> bool:
        """Without rotation, x growing with columns and y falling with rows."""
        t = self.transform
        return t.b == 0 and t.d == 0 and t.a > 0 and t.e < 0

    @property
    def bounds(self) -> Extent:
        """The grid's world rectangle (a north-up grid's)."""
        return self.window_bounds(Window(0, 0, self.width, self.height))

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    def xy(self, col, row):
        """World (x, y) of pixel position (col, row) (corners at integers; scalars or arrays)."""
        return self.transform @ (col, row)

    def colrow(self, x, y):
        """Fractional pixel position (col, row) of world (x, y) (scalars or arrays); see the module docstring."""
        t = self.transform
        if t.b == 0 and t.d == 0:
            return (x - t.c) / t.a, (y - t.f) / t.e
        return ~t @ (x, y)

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        """(col, row) of the cell holding world (x, y), clamped to the grid."""
        col, row = self.colrow(x, y)
        return min(max(int(col), 0), self.width - 1), min(max(int(row), 0), self.height - 1)

    def column_x(self) -> np.ndarray:
        """(width,) float64 x of the cell centres of each column."""
        return self.transform.c + (np.arange(self.width) + 0.5) * self.transform.a

    def row_y(self) -> np.ndarray:
        """(height,) float64 y of the cell centres of each row (row 0 is north)."""
        return self.transform.f + (np.arange(self.height) + 0.5) * self.transform.e

    def cell_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(height, width) float64 x and y of every cell centre."""
        return np.meshgrid(self.column_x(), self.row_y())

    def window(self, rows: slice, cols: slice) -> "Grid":
        """The grid of the cells ``rows`` x ``cols`` (half-open slices within this grid)."""
        return Grid(self.transform @ Affine.translation(cols.start, rows.start),
                    cols.stop - cols.start, rows.stop - rows.start)

    def window_bounds(self, win: Window) -> Extent:
        """The world rectangle of a pixel window (of a north-up grid)."""
        x0, y1 = self.xy(win.col0, win.row0)
        x1, y0 = self.xy(win.col1, win.row1)
        return Extent(x0, y0, x1, y1)

    def window_covering(self, e: Extent, pad: int = 0) -> Window:
        """The pixel window (possibly reaching past the grid) of the cells a world rectangle
        touches, grown by ``pad`` cells on every side (of a north-up grid)."""
        c0, r0 = self.colrow(e.xmin, e.ymax)
        c1, r1 = self.colrow(e.xmax, e.ymin)
        return Window(math.floor(c0) - pad, math.floor(r0) - pad, math.ceil(c1) + pad, math.ceil(r1) + pad)


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
                align: int = 1, halve: bool = False) -> list[Block]:
    """Cores tiling a height x width grid, each with a window ``margin`` cells wider on every side.

    A grid of at most ``max_cells`` cells is one block (so small scenes are processed whole).
    Otherwise each axis is cut into about equal spans so that a window is about
    sqrt(max_cells) cells wide; cuts fall only at ``row_cuts``/``col_cuts`` (default: multiples
    of TIFF_TILE, so each block written fills whole GeoTIFF tiles). ``align``: windows start
    (columns) and end (rows, counted from the grid's bottom row) at multiples of it, which keeps
    the CSF's cloth grid, anchored at the lower-left point, where the whole grid has it.
    ``halve``: a grid of one block whose longer side spans at least :data:`HALVE_SPANS` margins is
    cut in two across that side, so that two cores share it (the layout still depends on the grid
    alone); each half's window is its half and one margin across the cut.
    """
    if height * width <= max_cells:
        if halve and max(height, width) >= HALVE_SPANS * margin:
            return _halves(height, width, margin, align)
        whole = (slice(0, height), slice(0, width))
        return [Block(whole, whole)]
    span = max(math.isqrt(max_cells) - 2 * margin, margin, TIFF_TILE)
    return [_block(r0, r1, c0, c1, height, width, margin, align)
            for r0, r1 in _spans(height, span, row_cuts) for c0, c1 in _spans(width, span, col_cuts)]


def _halves(height: int, width: int, margin: int, align: int = 1) -> list[Block]:
    """Two blocks (:func:`cell_blocks`' windows) of a height x width grid, cut across its longer
    side at the multiple of TIFF_TILE nearest its middle; one block when that side has none."""
    rows = height > width
    cut = _spans(height if rows else width, math.ceil(max(height, width) / 2), None)
    if rows:
        return [_block(r0, r1, 0, width, height, width, margin, align) for r0, r1 in cut]
    return [_block(0, height, c0, c1, height, width, margin, align) for c0, c1 in cut]


def _block(r0: int, r1: int, c0: int, c1: int, height: int, width: int, margin: int, align: int) -> Block:
    """The block of core rows r0..r1, columns c0..c1: its window ``margin`` cells wider on every
    side within the grid, aligned as :func:`cell_blocks` says."""
    c_start = max(c0 - margin, 0)
    r_stop = min(r1 + margin, height)
    window = (slice(max(r0 - margin, 0), r_stop + (height - r_stop) % align),
              slice(c_start - c_start % align, min(c1 + margin, width)))
    return Block((slice(r0, r1), slice(c0, c1)), window)


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


def windows_meeting(reads: np.ndarray, windows: Sequence[Window], grid: Grid, cell: int = 64) -> np.ndarray:
    """Whether each of the (n, 4) pixel windows ``reads`` (col0, row0, col1, row1) of ``grid`` may
    meet one of ``windows``: both taken to squares of ``cell`` px, a read window meeting a square
    that a window covers part of. Never False where they meet (True at most a square early), in
    memory of the grid's squares, not of reads x windows (the web-tile cut: its base tiles' read
    windows against its changed windows and its blocks, 10^5 and 10^4 for a city at 5 cm)."""
    reads = np.asarray(reads, dtype=np.int64).reshape(-1, 4)
    ny, nx = -(-grid.height // cell), -(-grid.width // cell)
    held = np.zeros((ny + 1, nx + 1), np.int64)          # a 2D difference array of the windows' squares
    for w in windows:
        w = w.clipped(grid.width, grid.height)
        c0, r0, c1, r1 = w.col0 // cell, w.row0 // cell, -(-w.col1 // cell), -(-w.row1 // cell)
        if c1 > c0 and r1 > r0:
            held[r0, c0] += 1
            held[r0, c1] -= 1
            held[r1, c0] -= 1
            held[r1, c1] += 1
    covered = (held.cumsum(axis=0).cumsum(axis=1)[:ny, :nx] > 0).astype(np.int64)
    sums = np.zeros((ny + 1, nx + 1), np.int64)          # its integral image: squares covered in a range
    sums[1:, 1:] = covered.cumsum(axis=0).cumsum(axis=1)
    c0, r0 = np.clip(reads[:, 0], 0, grid.width) // cell, np.clip(reads[:, 1], 0, grid.height) // cell
    c1 = -(-np.clip(reads[:, 2], 0, grid.width) // cell)
    r1 = -(-np.clip(reads[:, 3], 0, grid.height) // cell)
    inside = (c1 > c0) & (r1 > r0)
    c0, r0, c1, r1 = (np.minimum(v, m) for v, m in ((c0, nx), (r0, ny), (c1, nx), (r1, ny)))
    return inside & (sums[r1, c1] - sums[r0, c1] - sums[r1, c0] + sums[r0, c0] > 0)
