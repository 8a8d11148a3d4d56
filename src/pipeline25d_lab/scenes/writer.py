"""What the generated scenes write alike: a DTM sampled from an exact terrain function (files: core.atomic)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import atomic_path


def write_dtm(path: Path, geotransform: tuple[float, ...], width: int, height: int,
              height_fn: Callable[[np.ndarray, np.ndarray], np.ndarray], epsg: int) -> None:
    """A float32 GeoTIFF of ``height_fn(x, y)`` at the pixel centres of a north-up grid, atomically."""
    from osgeo import osr

    from pipeline25d.core.raster import gdal

    g = gdal()
    gt = geotransform
    cols = gt[0] + (np.arange(width) + 0.5) * gt[1]
    rows = gt[3] + (np.arange(height) + 0.5) * gt[5]
    z = np.asarray(height_fn(cols[None, :], rows[:, None])).astype(np.float32)
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(epsg)
    with atomic_path(path) as tmp:
        ds = g.GetDriverByName("GTiff").Create(
            str(tmp), width, height, 1, g.GDT_Float32, ["COMPRESS=DEFLATE", "PREDICTOR=3", "TILED=YES"])
        ds.SetGeoTransform(gt)
        ds.SetProjection(srs.ExportToWkt())
        ds.GetRasterBand(1).WriteArray(z)
        ds.FlushCache()
        ds = None  # closes the file
