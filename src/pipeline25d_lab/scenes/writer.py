"""What the generated scenes write alike: a DTM sampled from an exact terrain function (files: core.atomic)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from pipeline25d.core.grid import Grid


def write_dtm(path: Path, grid: Grid, height_fn: Callable[[np.ndarray, np.ndarray], np.ndarray], epsg: int) -> None:
    """A float32 GeoTIFF of ``height_fn(x, y)`` at the cell centres of a north-up grid, atomically."""
    from osgeo import osr

    from pipeline25d.core.geotiff import write_geotiff

    z = np.asarray(height_fn(grid.column_x()[None, :], grid.row_y()[:, None])).astype(np.float32)
    srs = osr.SpatialReference()
    srs.ImportFromEPSG(epsg)
    write_geotiff(path, z, grid, srs.ExportToWkt(), "Float32", ["COMPRESS=DEFLATE", "PREDICTOR=3", "TILED=YES"])
