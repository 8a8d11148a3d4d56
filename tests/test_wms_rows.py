"""The WMS id layer's row raster (publish.wms_ids.row_raster): each id's row in the objects table,
looked up once per run of equal ids, against a lookup of every pixel."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline25d.core.errors import InputFileError
from pipeline25d.core.geotiff import write_geotiff
from pipeline25d.core.grid import Grid
from pipeline25d.core.raster import gdal
from pipeline25d.publish.wms_ids import row_raster


def id_image(rng: np.random.Generator, table: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Ids in runs of 1 to 40 pixels (0: none), as a map's rows hold them."""
    n = shape[0] * shape[1]
    lengths = rng.integers(1, 40, n // 10)
    values = np.where(rng.random(len(lengths)) < 0.2, 0, rng.choice(table, len(lengths)))
    return np.repeat(values, lengths)[:n].reshape(shape).astype(np.uint32)


def test_rows_equal_a_lookup_of_every_pixel_and_an_unknown_id_is_named(tmp_path: Path):
    rng = np.random.default_rng(7)
    table = np.unique(rng.integers(1, 2**32 - 1, 500, dtype=np.uint64)).astype(np.uint32)
    ids = id_image(rng, table, (300, 257))
    grid = Grid.from_gdal((1000.0, 0.5, 0.0, 2000.0, 0.0, -0.5), 257, 300)
    write_geotiff(tmp_path / "ids.tif", ids, grid, "", "UInt32", ("TILED=YES",), nodata=0)
    row_raster(tmp_path / "ids.tif", table.tolist(), tmp_path / "rows.tif", rows_per_block=64)
    got = gdal().Open(str(tmp_path / "rows.tif")).ReadAsArray()
    want = np.where(ids == 0, 0, np.searchsorted(table, ids) + 1)
    assert np.array_equal(got, want) and (got > 0).mean() > 0.5
    assert np.array_equal(table[got[got > 0] - 1], ids[got > 0])

    ids[150, 3:9], ids[200, 0] = 12345, 54321             # not in the table; the first in row order is named
    ids[150, 9] = table[0]
    assert 12345 not in table and 54321 not in table
    write_geotiff(tmp_path / "bad.tif", ids, grid, "", "UInt32", ("TILED=YES",), nodata=0)
    with pytest.raises(InputFileError, match="id 12345 is not in the objects table"):
        row_raster(tmp_path / "bad.tif", table.tolist(), tmp_path / "bad_rows.tif", rows_per_block=64)
