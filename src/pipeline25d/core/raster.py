"""GDAL access, DTM sampling and map change digests (GeoTIFFs are written by core.geotiff).

``gdal.UseExceptions()`` is called once here, so GDAL errors raise instead of returning None.
"""

from __future__ import annotations

import hashlib
import os
from functools import lru_cache
from pathlib import Path

import numpy as np

from pipeline25d.core.errors import InputFileError
from pipeline25d.core.grid import Extent, Grid, Window

CELL_PX = 128          # the map is compared with the one last cut in squares of this many pixels
READ_ROWS = 1024       # map_cells reads windows of at least this many rows ...
READ_PX = 1 << 22      # ... and about this many pixels
CACHE_MB = 256      # GDAL's block cache per job (its default, 5 % of RAM, is what a sparse map's COG filled)


@lru_cache(maxsize=1)
def gdal():
    """The osgeo.gdal module with exceptions enabled (imported on first use), its block cache
    capped at :data:`CACHE_MB` unless ``GDAL_CACHEMAX`` is set: a job's memory then does not
    grow with the size of the rasters it writes."""
    from osgeo import gdal as _gdal

    _gdal.UseExceptions()
    if "GDAL_CACHEMAX" not in os.environ and _gdal.GetCacheMax() > CACHE_MB << 20:
        _gdal.SetCacheMax(CACHE_MB << 20)
    return _gdal


def tool_env() -> dict[str, str]:
    """The environment of a GDAL command-line tool: this one, with the same block cache cap."""
    return {"GDAL_CACHEMAX": str(CACHE_MB), **os.environ}


def dataset_bounds(ds) -> Extent:
    """The world rectangle of a north-up GDAL dataset."""
    return Grid.of_dataset(ds).bounds


def window_alpha(ds, arr: np.ndarray, col: int, row: int, width: int, height: int) -> np.ndarray:
    """(h, w) uint8 opacity of a window read as ``arr`` (bands first): the alpha band of an
    RGBA map, else its per-dataset mask (a JPEG-compressed map keeps its alpha there), else opaque."""
    if arr.ndim == 3 and arr.shape[0] >= 4:
        return arr[3]
    g = gdal()
    band = ds.GetRasterBand(1)
    flags = band.GetMaskFlags()
    if flags & g.GMF_PER_DATASET and not flags & g.GMF_ALL_VALID:
        return band.GetMaskBand().ReadAsArray(col, row, width, height)
    return np.full((height, width), 255, np.uint8)


def read_rgba_block(ds, col0: int, row0: int, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(rgb float32 (h, w, 3), alpha uint8 (h, w)) of a window that may reach past the raster
    (outside: alpha 0, colour 0); a one-band raster is grey in all three channels."""
    rgb = np.zeros((height, width, 3), np.float32)
    alpha = np.zeros((height, width), np.uint8)
    c0, r0 = max(col0, 0), max(row0, 0)
    c1, r1 = min(col0 + width, ds.RasterXSize), min(row0 + height, ds.RasterYSize)
    if c1 <= c0 or r1 <= r0:
        return rgb, alpha
    arr = ds.ReadAsArray(c0, r0, c1 - c0, r1 - r0)
    if arr.ndim == 2:
        arr = arr[None]
    inner = (slice(r0 - row0, r1 - row0), slice(c0 - col0, c1 - col0))
    rgb[inner] = np.moveaxis(arr[:3] if arr.shape[0] >= 3 else np.repeat(arr[:1], 3, axis=0), 0, -1)
    alpha[inner] = window_alpha(ds, arr, c0, r0, c1 - c0, r1 - r0)
    return rgb, alpha


def stores_nothing(band, win: Window) -> bool:
    """Whether a GDAL ``band`` stores no block in the pixel window ``win``: a sparse GeoTIFF's or
    COG's unstored blocks, which GDAL reads as zeros (its data coverage EMPTY)."""
    status = band.GetDataCoverageStatus(win.col0, win.row0, win.width, win.height)[0]
    return status == gdal().GDAL_DATA_COVERAGE_STATUS_EMPTY


class DTM:
    """A terrain GeoTIFF sampled bilinearly in the scene CRS.

    Points are transformed to the raster's CRS first (pyproj), so a DTM in any CRS GDAL
    reads works; its heights are read as metres (a 2D CRS in feet has them in feet:
    :func:`~pipeline25d.core.crs.z_unit`). Cells equal to nodata give NaN, and so do points
    outside the raster, unless ``continuous``: then nodata cells take their nearest valid value
    and points outside take the nearest edge, so every vertex of a model has a ground height
    (terrain-relative projection needs one).
    """

    def __init__(self, path: str | Path, scene_crs: str, continuous: bool = False,
                 window: Extent | None = None):
        """``window``: (xmin, ymin, xmax, ymax) in the scene CRS: read only the cells around it
        (memory O(window), not O(raster)); points outside it are then clamped to its edge. A
        continuous DTM with nodata inside the window is read whole (see below)."""
        g = gdal()
        self.path = Path(path)
        try:
            ds = g.Open(str(path))
        except RuntimeError as exc:
            raise InputFileError(path, f"cannot open as a raster: {exc}") from None
        band = ds.GetRasterBand(1)
        grid = Grid.of_dataset(ds)
        if grid.transform.b or grid.transform.d:
            raise InputFileError(path, "rotated geotransforms are not supported")
        self.crs_wkt = ds.GetProjection()
        self.scene_crs = scene_crs
        win = Window(0, 0, grid.width, grid.height) if window is None else self._pixel_window(Extent(*window), grid)
        nodata = band.GetNoDataValue()

        from pipeline25d.core.crs import z_unit

        metres = z_unit(self.crs_wkt)[1] if self.crs_wkt else 1.0   # a DTM in a 2D CRS in feet: feet

        def read(w: Window) -> np.ndarray:      # nodata (a number, or NaN itself) as NaN; metres
            values = band.ReadAsArray(w.col0, w.row0, w.width, w.height).astype(np.float64)
            if nodata is not None:
                values[values == nodata] = np.nan
            return values * metres if metres != 1.0 else values

        self.values = read(win)
        if continuous and window is not None and not np.isfinite(self.values).all():
            # holes are filled from the nearest valid cell, which may lie outside the window:
            # read everything, so every tile fills them alike (no seams)
            win = Window(0, 0, grid.width, grid.height)
            self.values = read(win)
        self.grid = grid.window(*win.slices)
        self.continuous = continuous
        if continuous:

            if not np.isfinite(self.values).any():
                raise InputFileError(path, "has no valid height")
            self.values = fill_nearest(self.values)

    def _pixel_window(self, window: Extent, grid: Grid, margin: int = 2) -> Window:
        """The raster cells covering a scene-CRS window, plus a margin."""
        from pipeline25d.core.crs import transform_points

        x0, y0, x1, y1 = window
        pts = np.array([[x0, y0, 0.0], [x0, y1, 0.0], [x1, y0, 0.0], [x1, y1, 0.0]])
        if self.crs_wkt:
            pts = transform_points(pts, self.scene_crs, self.crs_wkt)
        cols, rows = grid.colrow(pts[:, 0], pts[:, 1])
        c0 = int(np.clip(np.floor(cols.min()) - margin, 0, grid.width - 1))
        r0 = int(np.clip(np.floor(rows.min()) - margin, 0, grid.height - 1))
        c1 = int(np.clip(np.ceil(cols.max()) + margin, c0 + 1, grid.width))
        r1 = int(np.clip(np.ceil(rows.max()) + margin, r0 + 1, grid.height))
        return Window(c0, r0, c1, r1)

    @classmethod
    def from_array(cls, values: np.ndarray, grid: Grid, continuous: bool = False) -> "DTM":
        """A DTM over an in-memory (h, w) height array on ``grid``, already in the scene CRS (NaN = nodata)."""
        self = cls.__new__(cls)
        self.path, self.grid, self.crs_wkt, self.scene_crs = Path("<memory>"), grid, "", None
        self.values = np.asarray(values, dtype=np.float64)
        self.continuous = continuous
        if continuous:

            self.values = fill_nearest(self.values)
        return self

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear heights at scene-CRS (x, y); NaN outside the raster or on nodata."""
        from pipeline25d.core.crs import transform_points

        pts = np.column_stack([x, y, np.zeros(len(x))])
        if self.crs_wkt:
            pts = transform_points(pts, self.scene_crs, self.crs_wkt)
        col, row = self.grid.colrow(pts[:, 0], pts[:, 1])
        col, row = col - 0.5, row - 0.5
        h, w = self.values.shape
        if self.continuous:
            col, row = np.clip(col, 0, max(w - 1.000001, 0)), np.clip(row, 0, max(h - 1.000001, 0))
            if w == 1 or h == 1:
                return self.values[np.clip(np.round(row).astype(int), 0, h - 1),
                                   np.clip(np.round(col).astype(int), 0, w - 1)]
        c0, r0 = np.floor(col).astype(int), np.floor(row).astype(int)
        ok = (c0 >= 0) & (r0 >= 0) & (c0 + 1 < w) & (r0 + 1 < h)
        out = np.full(len(x), np.nan)
        c0, r0, fc, fr = c0[ok], r0[ok], col[ok] - c0[ok], row[ok] - r0[ok]
        v = self.values
        out[ok] = ((v[r0, c0] * (1 - fc) + v[r0, c0 + 1] * fc) * (1 - fr)
                   + (v[r0 + 1, c0] * (1 - fc) + v[r0 + 1, c0 + 1] * fc) * fr)
        return out

def fill_nearest(values: np.ndarray, reach_cells: float | None = None) -> np.ndarray:
    """NaN cells take the value of the nearest finite cell (all-NaN input stays NaN); with
    ``reach_cells``, only those within that many cells of one."""
    bad = ~np.isfinite(values)
    if not bad.any() or bad.all():
        return values.copy()
    from scipy import ndimage as ndi  # only when needed: tile jobs read DTMs without holes

    if reach_cells is None:
        idx = ndi.distance_transform_edt(bad, return_distances=False, return_indices=True)
        return values[tuple(idx)]
    dist, idx = ndi.distance_transform_edt(bad, return_indices=True)
    out = values[tuple(idx)]
    out[dist > reach_cells] = np.nan
    return out

def run_starts(flat: np.ndarray) -> np.ndarray:
    """Indices where a 1-D array starts a run of equal values (0 first): object ids come in runs
    along a row, so what is done per id can be done per run."""
    return np.concatenate(([0], np.flatnonzero(flat[1:] != flat[:-1]) + 1))


def map_cells(cog: str | Path, cell: int = CELL_PX, memo: dict | None = None) -> tuple[list, dict[str, str]]:
    """The map's grid [*geotransform, width, height, cell] and a digest of each ``cell`` x ``cell``
    pixel square of it that holds data ({"col_row": digest}), read block by block. ``memo``: a
    job's own dict of what it has digested already (the warp job digests its mosaic for the map
    and again for the id map)."""
    if memo is not None:
        key = (str(cog), cell)
        if key not in memo:
            memo[key] = map_cells(cog, cell)
        return memo[key]
    ds = gdal().Open(str(cog))
    width, height = ds.RasterXSize, ds.RasterYSize
    bw, bh = ds.GetRasterBand(1).GetBlockSize()
    # windows of whole blocks and cells, at least READ_ROWS rows (a VRT's 128-px blocks cost a read each)
    step_y = max(cell, bh // cell * cell, READ_ROWS // cell * cell)
    step_x = max(cell, bw // cell * cell, READ_PX // step_y // cell * cell)
    digests = {}
    for r in range(0, height, step_y):
        for c in range(0, width, step_x):
            digests.update(window_cells(ds, Window(c, r, min(c + step_x, width), min(r + step_y, height)), cell))
    return cells_grid(Grid.of_dataset(ds), cell), digests


def write_cells_note(note: str | Path, raster: str | Path, grid: list, digests: dict[str, str]) -> None:
    """Keep :func:`map_cells`' result for ``raster`` (a map whose writer digested its pixels as it made
    them) in ``note``, with the file's size and sha256, so a later reader need not decode it again."""
    from pipeline25d.core.atomic import write_json

    write_json(note, {"raster": file_fingerprint(raster), "grid": grid, "cells": digests}, indent=None)


def noted_cells(note: str | Path | None, raster: str | Path) -> tuple[list, dict[str, str]] | None:
    """:func:`map_cells` of ``raster`` as :func:`write_cells_note` kept it, or None where there is no
    note or it is of another file (its size or sha256 differ: hashing the file costs a fifth of
    decoding it; its mtime would not do, as Snakemake touches a job's outputs when it ends)."""
    import json

    if note is None or not Path(note).is_file():
        return None
    try:
        kept = json.loads(Path(note).read_text())
    except (OSError, ValueError):
        return None
    if kept.get("raster") != file_fingerprint(raster):
        return None
    return kept["grid"], kept["cells"]


def file_fingerprint(path: str | Path) -> list:
    """[size, sha256 hex] of a file."""
    with open(path, "rb") as fh:
        return [os.fstat(fh.fileno()).st_size, hashlib.file_digest(fh, "sha256").hexdigest()]


def cells_grid(grid: Grid, cell: int = CELL_PX) -> list:
    """:func:`map_cells`' grid [*geotransform, width, height, cell] of a map on ``grid``."""
    return [*grid.geotransform, grid.width, grid.height, cell]


def window_cells(ds, win: Window, cell: int = CELL_PX, at: tuple[int, int] = (0, 0)) -> dict[str, str]:
    """:func:`map_cells`' digests of the squares in window ``win`` of the open dataset ``ds``, whose
    pixel (0, 0) is pixel ``at`` (col, row) of the map. ``win`` and ``at`` start on whole cells, so
    a map's digests are the same whether read at once or window by window (a block of it, say)."""
    g = gdal()
    c, r, w, h = win.col0, win.row0, win.width, win.height
    band = ds.GetRasterBand(1)
    # an alpha band is its own mask: read once (a VRT reads each band's sources per window)
    alpha_band = ds.RasterCount > 1 and band.GetMaskFlags() == g.GMF_ALPHA | g.GMF_PER_DATASET
    if alpha_band:
        bands = ds.ReadAsArray(c, r, w, h)
        alpha = bands[-1]
    else:
        alpha = band.GetMaskBand().ReadAsArray(c, r, w, h)
    if not alpha.any():
        return {}
    if not alpha_band:
        bands = ds.ReadAsArray(c, r, w, h)
    pixels = np.concatenate([bands.reshape(-1, h, w), alpha[None]])
    col0, row0 = at[0] + c, at[1] + r
    digests = {}
    for y in range(0, h, cell):
        for x in range(0, w, cell):
            if alpha[y:y + cell, x:x + cell].any():
                digest = hashlib.sha256(np.ascontiguousarray(pixels[:, y:y + cell, x:x + cell])).hexdigest()
                digests[f"{(col0 + x) // cell}_{(row0 + y) // cell}"] = digest[:16]
    return digests


def cells_grid_of(cells_grid: list) -> Grid:
    """The map's grid from :func:`map_cells`' [*geotransform, width, height, cell]."""
    return Grid.from_gdal(cells_grid[:6], cells_grid[6], cells_grid[7])
