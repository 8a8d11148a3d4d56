"""The WMS id layer's row raster (publish.wms_ids.row_raster): each id's row in the objects table,
looked up once per run of equal ids, against a lookup of every pixel; a sparse id raster's
unstored squares left unread and unstored."""

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
    row_raster(tmp_path / "ids.tif", table.tolist(), tmp_path / "rows.tif", block_px=64)
    got = gdal().Open(str(tmp_path / "rows.tif")).ReadAsArray()
    want = np.where(ids == 0, 0, np.searchsorted(table, ids) + 1)
    assert np.array_equal(got, want) and (got > 0).mean() > 0.5
    assert np.array_equal(table[got[got > 0] - 1], ids[got > 0])

    ids[150, 3:9], ids[200, 0] = 12345, 54321             # not in the table; the first in row order is named
    ids[150, 9] = table[0]
    assert 12345 not in table and 54321 not in table
    write_geotiff(tmp_path / "bad.tif", ids, grid, "", "UInt32", ("TILED=YES",), nodata=0)
    with pytest.raises(InputFileError, match="id 12345 is not in the objects table"):
        row_raster(tmp_path / "bad.tif", table.tolist(), tmp_path / "bad_rows.tif", block_px=64)


def test_the_rows_of_a_sparse_id_raster_skip_its_unstored_squares(tmp_path: Path):
    """Ids in one corner of a sparse COG (its empty blocks unstored, as the warp writes id maps):
    the row raster equals the lookup of every pixel and stores nothing where the ids store nothing."""
    rng = np.random.default_rng(3)
    table = np.arange(1, 200, 3, dtype=np.uint32)
    ids = np.zeros((1024, 1536), np.uint32)
    ids[:300, :400] = id_image(rng, table, (300, 400))
    grid = Grid.from_gdal((1000.0, 0.5, 0.0, 2000.0, 0.0, -0.5), 1536, 1024)
    write_geotiff(tmp_path / "dense.tif", ids, grid, "", "UInt32", ("TILED=YES",), nodata=0)
    gdal().Translate(str(tmp_path / "ids.tif"), str(tmp_path / "dense.tif"), format="COG",
                     creationOptions=["COMPRESS=DEFLATE", "SPARSE_OK=TRUE"])
    row_raster(tmp_path / "ids.tif", table.tolist(), tmp_path / "rows.tif", block_px=256)
    ds = gdal().Open(str(tmp_path / "rows.tif"))
    got = ds.ReadAsArray()
    assert np.array_equal(got, np.where(ids == 0, 0, np.searchsorted(table, ids) + 1)) and got.any()
    empty, data = gdal().GDAL_DATA_COVERAGE_STATUS_EMPTY, gdal().GDAL_DATA_COVERAGE_STATUS_DATA
    band = ds.GetRasterBand(1)
    assert band.GetDataCoverageStatus(512, 512, 1024, 512)[0] == empty
    assert band.GetDataCoverageStatus(0, 0, 256, 256)[0] & data
