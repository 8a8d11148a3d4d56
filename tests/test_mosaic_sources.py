"""The mosaic VRT's sources become plain copies where its tiles do not overlap, and it reads the
same pixels and masks as gdalbuildvrt's compositing sources; overlapping tiles keep those."""

from __future__ import annotations

import numpy as np

from pipeline25d.core.crs import horizontal_wkt
from pipeline25d.core.geotiff import write_geotiff, write_rgba_geotiff
from pipeline25d.core.grid import Grid
from pipeline25d.core.raster import gdal
from pipeline25d.stages.maps.mosaic_sources import build_mosaic, plain_sources
from pipeline25d.stages.maps.warp import run_tool

GSD, TILE, CRS = 0.5, 64, "EPSG:25832"


def _tiles(d, spots: list[tuple[float, float, int, int]], ids: bool = False) -> list[str]:
    """Tiles at (x, y) of their top-left corner and (w, h) px: random colours, a random alpha with
    0 in about a third of the pixels (colour under it too: the writer must clear it), or ids."""
    paths = []
    for k, (x, y, w, h) in enumerate(spots):
        rng = np.random.default_rng(k)
        grid = Grid.north_up(x, y, GSD, w, h)
        path = d / (f"{k}.ids.tif" if ids else f"{k}.tif")
        if ids:
            values = rng.integers(1, 1 << 30, (h, w), dtype=np.uint32)
            values[rng.random((h, w)) < 0.3] = 0
            write_geotiff(path, values, grid, horizontal_wkt(CRS), "UInt32", ("COMPRESS=DEFLATE", "TILED=YES"),
                          nodata=0)
        else:
            rgba = rng.integers(0, 256, (h, w, 4), dtype=np.uint8)
            rgba[..., 3][rng.random((h, w)) < 0.3] = 0
            write_rgba_geotiff(path, rgba, grid, horizontal_wkt(CRS))
        paths.append(str(path))
    return paths


def _read(vrt) -> tuple[np.ndarray, np.ndarray]:
    ds = gdal().Open(str(vrt))
    return ds.ReadAsArray(), ds.GetRasterBand(1).GetMaskBand().ReadAsArray()


DISJOINT = [(0.0, 64.0, 64, 64), (32.0, 64.0, 40, 64), (0.0, 32.0, 64, 17), (52.0, 20.0, 9, 30)]   # a gap too


def test_disjoint_tiles_read_the_same_through_plain_copies(tmp_path):
    for ids in (False, True):
        tiles = _tiles(tmp_path, DISJOINT, ids)
        composite, plain = tmp_path / "composite.vrt", tmp_path / "plain.vrt"
        run_tool(["gdalbuildvrt", "-q", str(composite), *tiles])
        build_mosaic(tiles, plain)
        text = plain.read_text()
        assert "SimpleSource" in text and "ComplexSource" not in text and "UseMaskBand" not in text
        assert "ComplexSource" in composite.read_text()
        (a, mask_a), (b, mask_b) = _read(composite), _read(plain)
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(mask_a, mask_b)
        assert (mask_a == 0).mean() > 0.25          # the masks have holes, and a gap between tiles
    rgba = gdal().Open(str(tmp_path / "0.tif")).ReadAsArray()
    assert rgba[3].min() == 0 and not rgba[:3][:, rgba[3] == 0].any()       # no colour stored under alpha 0


def test_overlapping_tiles_keep_their_compositing_sources(tmp_path):
    tiles = _tiles(tmp_path, [(0.0, 64.0, 64, 64), (31.5, 64.0, 40, 64)])     # one column shared
    vrt = tmp_path / "m.vrt"
    run_tool(["gdalbuildvrt", "-q", str(vrt), *tiles])
    before = vrt.read_text()
    assert plain_sources(vrt) is False and vrt.read_text() == before
    built = tmp_path / "built.vrt"
    build_mosaic(tiles, built)                  # GDAL's BuildVRT in this process: the tool's VRT, to the byte
    assert built.read_text() == before.replace(str(vrt.parent), str(built.parent))
