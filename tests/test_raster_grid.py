"""The raster layer: Grid (affine transform) pixel <-> world against hand arithmetic, Window and
Extent, and the one GeoTIFF writer read back with GDAL (and byte-equal to direct GDAL calls)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from affine import Affine

from pipeline25d.core.geotiff import float_geotiff_writer, geotiff_dataset, write_geotiff, write_rgba_geotiff
from pipeline25d.core.grid import Extent, Grid, Window
from pipeline25d.core.raster import dataset_bounds, gdal

X0, Y1, RES = 691000.25, 5334000.5, 0.5


def test_pixel_world_round_trip_and_hand_arithmetic():
    grid = Grid.north_up(X0, Y1, RES, 300, 200)
    assert grid.geotransform == (X0, RES, 0.0, Y1, 0.0, -RES)
    assert grid.transform == Affine(RES, 0.0, X0, 0.0, -RES, Y1)
    rng = np.random.default_rng(0)
    col, row = rng.uniform(0, 300, 50), rng.uniform(0, 200, 50)
    x, y = grid.xy(col, row)
    np.testing.assert_array_equal(x, X0 + col * RES)
    np.testing.assert_array_equal(y, Y1 - row * RES)
    c2, r2 = grid.colrow(x, y)
    np.testing.assert_allclose(c2, col, atol=1e-9)
    np.testing.assert_allclose(r2, row, atol=1e-9)
    assert grid.colrow(X0 + 3 * RES, Y1 - 7 * RES) == (3.0, 7.0)        # exact at cell corners
    assert grid.cell_of(X0 - 5, Y1 + 5) == (0, 0) and grid.cell_of(X0 + 1e6, Y1 - 1e6) == (299, 199)
    np.testing.assert_array_equal(grid.column_x()[:2], [X0 + 0.25, X0 + 0.75])
    np.testing.assert_array_equal(grid.row_y()[:2], [Y1 - 0.25, Y1 - 0.75])


def test_rotated_grid_inverts_through_the_affine():
    grid = Grid(Affine.translation(100.0, 200.0) @ Affine.rotation(30.0) @ Affine.scale(2.0, -2.0), 10, 10)
    c, r = grid.colrow(*grid.xy(np.array([1.5, 7.0]), np.array([2.0, 9.5])))
    np.testing.assert_allclose(c, [1.5, 7.0], atol=1e-9)
    np.testing.assert_allclose(r, [2.0, 9.5], atol=1e-9)
    assert not grid.is_north_up and Grid.north_up(0, 0, 1, 1, 1).is_north_up


def test_windows_bounds_and_subgrids():
    grid = Grid.north_up(X0, Y1, RES, 300, 200)
    win = Window(10, 20, 110, 70)
    assert (win.width, win.height) == (100, 50) and Window.of_slices(*win.slices) == win
    assert grid.window_bounds(win) == Extent(X0 + 5.0, Y1 - 35.0, X0 + 55.0, Y1 - 10.0)
    sub = grid.window(*win.slices)
    assert (sub.xmin, sub.ymax, sub.res, sub.width, sub.height) == (X0 + 5.0, Y1 - 10.0, RES, 100, 50)
    assert sub.bounds == grid.window_bounds(win)
    # the cells a rectangle touches, grown by a pad
    assert grid.window_covering(Extent(X0 + 5.1, Y1 - 34.9, X0 + 54.9, Y1 - 10.1), pad=2) == Window(8, 18, 112, 72)
    assert grid.bounds.width == 150.0 and grid.bounds.height == 100.0


def test_covering_snaps_outward_to_the_resolution():
    grid = Grid.covering((10.3, 20.6, 15.1, 23.0), 0.5)
    assert (grid.xmin, grid.ymax, grid.width, grid.height) == (10.0, 23.0, math.ceil(15.1 / 0.5) - 20, 5)


def test_dataset_grid_and_bounds(tmp_path):
    values = np.arange(12, dtype=np.float32).reshape(3, 4)
    grid = Grid.north_up(X0, Y1, RES, 4, 3)
    write_geotiff(tmp_path / "a.tif", values, grid, "", "Float32")
    ds = gdal().Open(str(tmp_path / "a.tif"))
    assert Grid.of_dataset(ds) == grid
    assert dataset_bounds(ds) == (X0, Y1 - 1.5, X0 + 2.0, Y1)
    np.testing.assert_array_equal(ds.GetRasterBand(1).ReadAsArray(), values)


def test_rgba_writer_reads_back_and_matches_direct_gdal_bytes(tmp_path):
    from pipeline25d.core.crs import horizontal_wkt

    rng = np.random.default_rng(1)
    rgba = rng.integers(0, 255, (300, 270, 4), dtype=np.uint8)
    rgba[..., 3] |= 1                  # no alpha 0: the writer clears the colour under it
                                       # (tests/test_mosaic_sources.py)
    grid = Grid.north_up(X0, Y1, RES, 270, 300)
    wkt = horizontal_wkt("EPSG:25832")
    write_rgba_geotiff(tmp_path / "ours.tif", rgba, grid, wkt)
    # the same file written with GDAL directly, as the writer did before it was shared
    g = gdal()
    ds = g.GetDriverByName("GTiff").Create(str(tmp_path / "ref.tif"), 270, 300, 4, g.GDT_Byte,
                                           ["COMPRESS=ZSTD", "ZSTD_LEVEL=1", "TILED=YES", "PHOTOMETRIC=RGB",
                                            "ALPHA=YES"])
    ds.SetGeoTransform((X0, RES, 0.0, Y1, 0.0, -RES))
    ds.SetProjection(wkt)
    for b, interp in enumerate((g.GCI_RedBand, g.GCI_GreenBand, g.GCI_BlueBand, g.GCI_AlphaBand)):
        ds.GetRasterBand(b + 1).SetColorInterpretation(interp)
        ds.GetRasterBand(b + 1).WriteArray(rgba[:, :, b])
    ds.FlushCache()
    ds = None
    assert (tmp_path / "ours.tif").read_bytes() == (tmp_path / "ref.tif").read_bytes()
    back = gdal().Open(str(tmp_path / "ours.tif"))
    np.testing.assert_array_equal(np.moveaxis(back.ReadAsArray(), 0, -1), rgba)
    assert back.GetRasterBand(4).GetColorInterpretation() == g.GCI_AlphaBand


def test_block_writer_is_atomic_sparse_and_keeps_nan(tmp_path):
    grid = Grid.north_up(X0, Y1, RES, 600, 300)
    values = np.full((300, 600), np.nan)
    values[10:40, 300:520] = np.linspace(0, 1, 30 * 220).reshape(30, 220)
    out = tmp_path / "f.tif"
    with float_geotiff_writer(out, grid, "") as write:
        write(values[:, :256], 0, 0)          # all NaN: not written
        write(values[:, 256:], 0, 256)
        assert not out.exists()               # appears only when the block writing ends
    ds = gdal().Open(str(out))
    assert ds.GetGeoTransform() == grid.geotransform and np.isnan(ds.GetRasterBand(1).GetNoDataValue())
    np.testing.assert_array_equal(ds.GetRasterBand(1).ReadAsArray(), values.astype(np.float32))


def test_failed_writing_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError):
        with geotiff_dataset(tmp_path / "x.tif", Grid.north_up(0, 10, 1, 10, 10), "", overviews=[2]) as out:
            out.band(1).WriteArray(np.ones((10, 10), np.uint8))
            raise RuntimeError("stop")
    assert list(tmp_path.iterdir()) == []


def test_map_cells_memo_digests_a_file_once_per_job(tmp_path):
    """With a memo (the warp job's, shared by its map and id map), a mosaic is digested once: a
    second call returns the first digests, even after the file changed; without it, it is read again."""
    from pipeline25d.core.crs import horizontal_wkt
    from pipeline25d.core.raster import map_cells

    rng = np.random.default_rng(5)
    grid, wkt, path = Grid.north_up(X0, Y1, RES, 300, 200), horizontal_wkt("EPSG:25832"), tmp_path / "m.tif"
    write_rgba_geotiff(path, rng.integers(1, 255, (200, 300, 4), dtype=np.uint8), grid, wkt)
    memo: dict = {}
    first = map_cells(path, memo=memo)
    assert len(first[1]) == 3 * 2 and first == map_cells(path)        # 128-px cells of 300 x 200 px
    write_rgba_geotiff(path, rng.integers(1, 255, (200, 300, 4), dtype=np.uint8), grid, wkt)
    assert map_cells(path, memo=memo) is first
    assert map_cells(path)[1].keys() == first[1].keys() and map_cells(path)[1] != first[1]


def test_windows_meeting_never_misses_a_meeting_and_is_exact_at_one_pixel_squares():
    """core.grid.windows_meeting against every pair compared: at squares of 1 px it is the pairwise
    answer; at 64 px it is True wherever that is, and False for reads farther than a square from
    every window; reads off the grid meet nothing. 10^5 reads against 10^4 windows (10^9 pairs) run
    in the memory of the grid's squares."""
    from pipeline25d.core.grid import Grid, Window, windows_meeting

    rng = np.random.default_rng(5)
    grid = Grid.north_up(0.0, 0.0, 1.0, 3000, 2000)

    def boxes(n: int, size: int) -> np.ndarray:
        c0, r0 = rng.integers(-50, 3000, n), rng.integers(-50, 2000, n)
        return np.column_stack([c0, r0, c0 + rng.integers(1, size, n), r0 + rng.integers(1, size, n)])

    reads, wins = boxes(4000, 300), [Window(*w) for w in boxes(40, 200)]
    w = np.asarray(wins)
    pairwise = ((reads[:, None, 0] < w[None, :, 2]) & (reads[:, None, 2] > w[None, :, 0])
                & (reads[:, None, 1] < w[None, :, 3]) & (reads[:, None, 3] > w[None, :, 1]))
    on_grid = (np.minimum(reads[:, 2], 3000) > np.maximum(reads[:, 0], 0)) & \
        (np.minimum(reads[:, 3], 2000) > np.maximum(reads[:, 1], 0))
    clipped = [Window(max(v.col0, 0), max(v.row0, 0), min(v.col1, 3000), min(v.row1, 2000)) for v in wins]
    c = np.asarray(clipped)
    exact = (pairwise & on_grid[:, None]
             & (c[None, :, 2] > c[None, :, 0]) & (c[None, :, 3] > c[None, :, 1])).any(axis=1)
    np.testing.assert_array_equal(windows_meeting(reads, wins, grid, cell=1), exact)
    coarse = windows_meeting(reads, wins, grid, cell=64)
    assert (coarse >= exact).all() and coarse.sum() > exact.sum() > 100
    grown = [Window(v.col0 - 64, v.row0 - 64, v.col1 + 64, v.row1 + 64) for v in clipped]
    g = np.asarray(grown)
    near = ((reads[:, None, 0] < g[None, :, 2]) & (reads[:, None, 2] > g[None, :, 0])
            & (reads[:, None, 1] < g[None, :, 3]) & (reads[:, None, 3] > g[None, :, 1])).any(axis=1)
    assert not (coarse & ~near).any()
    many = windows_meeting(boxes(100_000, 256), [Window(*v) for v in boxes(10_000, 1024)], grid)
    assert many.shape == (100_000,) and many.any() and not many.all()
