"""Reading the maps: opened once, windows as grey values and opacity, the two maps' grids paired."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline25d.core.errors import InputFileError
from pipeline25d.core.grid import Grid, Window
from pipeline25d.core.raster import gdal, read_rgba_block, window_alpha

log = logging.getLogger(__name__)

_GREY = np.array([0.299, 0.587, 0.114])


_ALIGN_TOL_PX = 1e-3          # origins closer than this to a whole-pixel offset count as aligned


_GSD_RTOL = 1e-6


def _open(path: str | Path):
    try:
        ds = gdal().Open(str(path))
    except RuntimeError as exc:
        raise InputFileError(path, f"cannot open as a raster: {exc}") from None
    grid = Grid.of_dataset(ds)
    if not grid.is_north_up:
        raise InputFileError(path, f"must be north-up without rotation, geotransform {grid.geotransform}")
    return ds


def _same_crs(wkt_a: str, wkt_b: str) -> bool:
    if not wkt_a or not wkt_b:
        return wkt_a == wkt_b
    from osgeo import osr

    a, b = osr.SpatialReference(), osr.SpatialReference()
    a.ImportFromWkt(wkt_a)
    b.ImportFromWkt(wkt_b)
    return bool(a.IsSame(b))


def _read_window(ds, col: int, row: int, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(grey float64, alpha uint8) of a size×size block at pixel (col, row); no alpha band = opaque."""
    arr = ds.ReadAsArray(col, row, size, size)
    if arr.ndim == 2:
        arr = arr[None]
    n = arr.shape[0]
    alpha = window_alpha(ds, arr, col, row, size, size)
    grey = np.tensordot(_GREY, arr[:3].astype(np.float64), axes=1) if n >= 3 else arr[0].astype(np.float64)
    return grey, alpha


@dataclass
class _Pairing:
    """How nadir pixels pair with oblique pixels over the overlap of the two maps."""

    src: Any                      # oblique dataset to read (the file, or an in-memory resampled copy)
    obl_off: tuple[int, int]      # (col, row) in ``src`` of the overlap's top-left pixel
    nad_off: tuple[int, int]      # (col, row) in the nadir map of the same pixel
    size: tuple[int, int]         # overlap (width, height), px
    frac: tuple[float, float]     # map position of oblique pixel minus paired nadir pixel, (east, south) px
    resampled: bool
    note: str


def _pair_grids(obl, nad, oblique_path) -> _Pairing:
    """Pair the oblique map's pixels with the nadir grid.

    Same gsd: each nadir pixel pairs with the nearest oblique pixel; a sub-pixel origin offset
    is kept in ``frac`` and added to measured offsets (exact, no resampling). Different gsd:
    the oblique map is resampled bilinearly onto the nadir grid in memory (noted and logged).
    """
    ng, og = Grid.of_dataset(nad), Grid.of_dataset(obl)
    tn, to = ng.transform, og.transform
    gsd_x, gsd_y = tn.a, -tn.e
    wn, hn, wo, ho = ng.width, ng.height, og.width, og.height
    same_gsd = abs(to.a - tn.a) <= _GSD_RTOL * gsd_x and abs(to.e - tn.e) <= _GSD_RTOL * gsd_y
    # oblique origin (and far corner) in nadir pixel coordinates
    ob = og.bounds
    c_lo, r_lo = ng.colrow(ob.xmin, ob.ymax)
    if same_gsd:
        kc, kr = round(c_lo), round(r_lo)
        fc, fr = c_lo - kc, r_lo - kr
        c0, r0 = max(0, kc), max(0, kr)
        w, h = max(0, min(wn, kc + wo) - c0), max(0, min(hn, kr + ho) - r0)
        note = ""
        if abs(fc) > _ALIGN_TOL_PX or abs(fr) > _ALIGN_TOL_PX:
            note = (f"oblique origin off the nadir grid by ({fc:+.3f}, {fr:+.3f}) px (east, south): windows "
                    "paired on the nearest pixels, the fraction added to the offsets (no resampling)")
            log.info("%s: %s", oblique_path, note)
        else:
            fc = fr = 0.0
        return _Pairing(obl, (c0 - kc, r0 - kr), (c0, r0), (w, h), (fc, fr), False, note)
    c_hi, r_hi = ng.colrow(ob.xmax, ob.ymin)
    c0, r0 = max(0, math.ceil(c_lo - _ALIGN_TOL_PX)), max(0, math.ceil(r_lo - _ALIGN_TOL_PX))
    c1, r1 = min(wn, math.floor(c_hi + _ALIGN_TOL_PX)), min(hn, math.floor(r_hi + _ALIGN_TOL_PX))
    w, h = max(0, c1 - c0), max(0, r1 - r0)
    if w == 0 or h == 0:
        return _Pairing(obl, (0, 0), (0, 0), (0, 0), (0.0, 0.0), False, "maps do not overlap")
    bounds = ng.window_bounds(Window(c0, r0, c1, r1))
    warped = gdal().Warp("", obl, format="MEM", outputBounds=bounds, width=w, height=h,
                         resampleAlg="bilinear", dstSRS=nad.GetProjection() or None)
    note = (f"oblique gsd {to.a:g} x {-to.e:g} m differs from the nadir gsd {gsd_x:g} x {gsd_y:g} m: "
            "resampled bilinearly onto the nadir grid (interpolation can bias sub-pixel offsets)")
    log.warning("%s: %s", oblique_path, note)
    return _Pairing(warped, (0, 0), (c0, r0), (w, h), (0.0, 0.0), True, note)


def _read_block(ds, col: int, row: int, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Like :func:`_read_window`, but the block may reach past the raster: outside is alpha 0, grey 0."""
    w, h = ds.RasterXSize, ds.RasterYSize
    if col >= 0 and row >= 0 and col + size <= w and row + size <= h:
        return _read_window(ds, col, row, size)
    rgb, alpha = read_rgba_block(ds, col, row, size, size)
    return np.tensordot(rgb.astype(np.float64), _GREY, axes=([2], [0])), alpha
