"""Maps of sparse scenes: the rendered tiles in parts, each part warped and reduced on its own.

A scene whose districts lie far apart would otherwise cost its bounding box in every raster
stage: the warp, the COG's overviews and the web tiles all walk the empty land between
them. Here a perspective's rendered tiles are grouped into *parts*, rectangles of tiles
within :data:`PART_GAP_TILES` of one another (overlapping rectangles merge). When the parts
cover less than :data:`DENSE_SHARE` of the tiles' bounding box, the map is assembled from
them: each part is warped onto the map's pixel grid with its own overviews, and the parts
are written into one sparse COG whose empty blocks are never stored. A part's window spans
its tiles' content boxes and starts and ends at multiples of the largest overview factor, so
every overview pixel of a part is the whole map's. Otherwise the map is one part, warped whole.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from pipeline25d.core.geotiff import geotiff_dataset
from pipeline25d.core.grid import Extent, Grid, Window
from pipeline25d.core.raster import gdal
from pipeline25d.stages.records import Plan

log = logging.getLogger(__name__)

PART_GAP_TILES = 1     # tiles at most this many empty tiles apart share a part
DENSE_SHARE = 0.5      # parts covering at least this share of the tiles' bounding box: one part
COG_BLOCK = 512        # the COG driver's block size; its overviews halve until they fit one block
EDGE_SAMPLES = 33      # points per part edge transformed to find its window on the map


def tile_parts(cells: Iterable[tuple[int, int]], gap: int = PART_GAP_TILES,
               dense_share: float = DENSE_SHARE) -> list[tuple[int, int, int, int]]:
    """Rectangles (row0, col0, row1, col1), inclusive, grouping the tiles (row, col).

    Tiles within ``gap`` empty tiles of one another share a rectangle, and rectangles that
    come within ``gap`` of each other merge. One rectangle, the tiles' bounding box, when the
    rectangles cover at least ``dense_share`` of it.
    """
    rc = np.array(sorted(set(cells)), dtype=np.int64).reshape(-1, 2)
    if not len(rc):
        raise ValueError("no tiles to group into parts")
    lo, hi = rc.min(axis=0), rc.max(axis=0)
    whole = [(int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1]))]
    if len(rc) >= dense_share * np.prod(hi - lo + 1):    # the tiles alone fill the share: rectangles can only add
        return whole
    from scipy import ndimage as ndi  # (its import costs more than a dense map's grouping)

    occupied = np.zeros(tuple(hi - lo + 1), bool)
    occupied[rc[:, 0] - lo[0], rc[:, 1] - lo[1]] = True
    grown = ndi.binary_dilation(occupied, np.ones((3, 3), bool), iterations=gap) if gap else occupied
    labels, _ = ndi.label(grown, np.ones((3, 3), bool))
    rects = []
    for k, (rs, cs) in enumerate(ndi.find_objects(labels), start=1):
        r, c = np.nonzero(occupied[rs, cs] & (labels[rs, cs] == k))
        rects.append([rs.start + r.min(), cs.start + c.min(), rs.start + r.max(), cs.start + c.max()])
    rects = _merge_close(rects, gap)
    area = sum((r1 - r0 + 1) * (c1 - c0 + 1) for r0, c0, r1, c1 in rects)
    if area >= dense_share * occupied.size:
        return whole
    return sorted((int(r0 + lo[0]), int(c0 + lo[1]), int(r1 + lo[0]), int(c1 + lo[1])) for r0, c0, r1, c1 in rects)


def _merge_close(rects: list[list[int]], gap: int) -> list[list[int]]:
    """Merge rectangles (inclusive corners) that overlap once grown by ``gap``, until none do."""
    merged = True
    while merged:
        merged = False
        for i in range(len(rects)):
            for j in range(i + 1, len(rects)):
                a, b = rects[i], rects[j]
                if (a[0] - gap <= b[2] and b[0] - gap <= a[2] and a[1] - gap <= b[3] and b[1] - gap <= a[3]):
                    rects[i] = [min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])]
                    del rects[j]
                    merged = True
                    break
            if merged:
                break
    return rects


def overview_factors(width: int, height: int, block: int = COG_BLOCK) -> list[int]:
    """The COG driver's overview factors: halve until the overview fits one block."""
    factors, f = [], 2
    while max(width, height) / (f // 2) > block:
        factors.append(f)
        f *= 2
    return factors


def box_outline(x0: float, y0: float, x1: float, y1: float, n: int = EDGE_SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """(xs, ys) of ``n`` points along each edge of a box, counter-clockwise from (x0, y0)."""
    t = np.linspace(0.0, 1.0, n)
    xs = np.concatenate([x0 + (x1 - x0) * t, np.full_like(t, x1), x1 - (x1 - x0) * t, np.full_like(t, x0)])
    ys = np.concatenate([np.full_like(t, y0), y0 + (y1 - y0) * t, np.full_like(t, y1), y1 - (y1 - y0) * t])
    return xs, ys


def part_bounds(plan: Plan, rects: list[tuple[int, int, int, int]], to_map) -> list[Extent]:
    """Each part's bounding box on the map (xmin, ymin, xmax, ymax) in the map CRS.

    A part spans its tiles' content boxes (see :mod:`pipeline25d.stages.plan`). ``to_map(x, y)``
    takes render-plane coordinates (the tiles' geotransform space) to the map's: the identity
    for an unwarped map, the chosen GCP warp otherwise. The part's outline is sampled, so a
    curved warp is followed.
    """
    out = []
    for r0, c0, r1, c1 in rects:
        boxes = np.array([t.content for t in plan.tiles if r0 <= t.row <= r1 and c0 <= t.col <= c1])
        x0, y0 = boxes[:, :2].min(axis=0)
        x1, y1 = boxes[:, 2:].max(axis=0)
        mx, my = to_map(*box_outline(x0, y0, x1, y1))
        out.append(Extent(float(np.min(mx)), float(np.min(my)), float(np.max(mx)), float(np.max(my))))
    return out


def map_grid(bounds: list[Extent], gsd: float, margin_px: int = 2) -> tuple[Grid, list[Window]]:
    """The map's grid and each part's window on it.

    Windows are the parts' bounds grown by ``margin_px`` and snapped outward to multiples of
    ``align`` pixels of a global grid (origin 0, 0), where ``align`` is the largest overview
    factor of the map, so each overview pixel lies within one part; the map is the windows' union.
    """
    align = 1
    while True:
        step = align * gsd
        snapped = [(math.floor((x0 - margin_px * gsd) / step), math.floor((y0 - margin_px * gsd) / step),
                    math.ceil((x1 + margin_px * gsd) / step), math.ceil((y1 + margin_px * gsd) / step))
                   for x0, y0, x1, y1 in bounds]
        gx0, gy0 = min(s[0] for s in snapped), min(s[1] for s in snapped)
        gx1, gy1 = max(s[2] for s in snapped), max(s[3] for s in snapped)
        width, height = (gx1 - gx0) * align, (gy1 - gy0) * align
        factors = overview_factors(width, height)
        if not factors or factors[-1] <= align:
            break
        align = factors[-1]
    grid = Grid.north_up(gx0 * step, gy1 * step, gsd, width, height)
    windows = [Window((sx0 - gx0) * align, (gy1 - sy1) * align, (sx1 - gx0) * align, (gy1 - sy0) * align)
               for sx0, sy0, sx1, sy1 in snapped]
    return grid, windows


def assemble_sparse_cog(parts: list[tuple[Path, Window]], grid: Grid, wkt: str, out: str | Path,
                        cog_options: list[str], rows_per_copy: int = 1024, ids: bool = False) -> None:
    """Write the parts' pixels and overviews into a COG on ``grid`` at ``out``.

    Each part raster (RGBA, or with ``ids`` one UInt32 band of object ids, nodata 0; on the map
    grid, with the map's overview factors already built)
    is copied into an intermediate sparse GeoTIFF, level by level, ``rows_per_copy`` rows at a
    time (memory O(part width)); the COG driver then keeps those overviews and skips the
    unstored blocks. ``cog_options``: the COG driver's compression, overview and sparse options
    (:func:`~pipeline25d.stages.maps.warp.cog_options`; OVERVIEWS=FORCE_USE_EXISTING keeps the parts' own).
    """
    g = gdal()
    factors = overview_factors(grid.width, grid.height)
    tmp = Path(out).with_suffix(".parts.tif")
    options = ["TILED=YES", f"BLOCKXSIZE={COG_BLOCK}", f"BLOCKYSIZE={COG_BLOCK}", "SPARSE_OK=TRUE", "COMPRESS=ZSTD",
               "ZSTD_LEVEL=1", "BIGTIFF=IF_SAFER", *([] if ids else ["ALPHA=YES", "PHOTOMETRIC=RGB"])]
    bands, dtype, nodata = (1, "UInt32", 0) if ids else (4, "Byte", None)
    try:
        with geotiff_dataset(tmp, grid, wkt, bands, dtype, options, nodata=nodata,
                             overviews=factors) as dst:  # levels filled below
            _copy_parts(parts, dst, factors, rows_per_copy, bands)
        g.Translate(str(out), str(tmp), format="COG",
                    creationOptions=[*cog_options, "BIGTIFF=IF_SAFER"])
    finally:
        tmp.unlink(missing_ok=True)


def _copy_parts(parts: list[tuple[Path, Window]], dst, factors: list[int], rows_per_copy: int, bands: int) -> None:
    """Each part's levels into the same levels of ``dst`` (a :class:`pipeline25d.core.geotiff.GeoTiffOut`)."""
    g = gdal()
    for path, win in parts:
        src = g.Open(str(path))
        for level, f in enumerate([1, *factors]):
            src_bands = [src.GetRasterBand(b + 1) for b in range(bands)]
            dst_bands = [dst.band(b + 1) for b in range(bands)]
            if level:
                src_bands = [b.GetOverview(level - 1) for b in src_bands]
                dst_bands = [b.GetOverview(level - 1) for b in dst_bands]
            w, h = src_bands[0].XSize, src_bands[0].YSize
            if (w, h) != (win.width // f, win.height // f):
                raise ValueError(f"{path}: level {f} is {w} x {h}, not the window's {win.width // f} x "
                                 f"{win.height // f}")
            for r in range(0, h, rows_per_copy):
                n = min(rows_per_copy, h - r)
                for sb, db in zip(src_bands, dst_bands):
                    db.WriteRaster(win.col0 // f, win.row0 // f + r, w, n, sb.ReadRaster(0, r, w, n))
        src = None
