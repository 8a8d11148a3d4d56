"""Sparse maps: tiles grouped into parts, parts warped alone and assembled into one sparse COG
that equals the map warped whole."""

from __future__ import annotations

import os

import numpy as np
import pytest
from conftest import grid_plan

from pipeline25d.core.geotiff import write_rgba_geotiff
from pipeline25d.core.grid import Grid
from pipeline25d.core.raster import gdal
from pipeline25d.stages.maps.mosaic_sources import build_mosaic
from pipeline25d.stages.maps.parts import COG_BLOCK, map_grid, overview_factors, tile_parts
from pipeline25d.stages.maps.warp import warp_to_cog
from pipeline25d.stages.records import Observation

GSD, TILE = 0.5, 128
CRS = "EPSG:25832"


def test_far_groups_are_parts_and_near_ones_merge():
    a = [(r, c) for r in range(3) for c in range(4)]
    b = [(r, c) for r in range(20, 22) for c in range(30, 33)]
    near = [(4, 2)]                                  # one empty row above a's top row: same part
    assert tile_parts(a + b + near) == [(0, 0, 4, 3), (20, 30, 21, 32)]
    assert tile_parts(a + [(5, 2)], gap=1) == [(0, 0, 5, 3)]   # parts whose rectangles come within the gap merge
    c = [(r, c) for r in range(5, 7) for c in range(4)]      # 2 empty rows from a: apart, but together
    assert tile_parts(a + c) == [(0, 0, 6, 3)]                 # they cover >= half their box: one part
    assert tile_parts([(7, 7)]) == [(7, 7, 7, 7)]
    with pytest.raises(ValueError):
        tile_parts([])


def test_parts_span_their_tiles_content_not_whole_tiles():
    from pipeline25d.stages.maps.parts import part_bounds

    span = TILE * GSD
    plan = grid_plan([(0, 0), (0, 1), (9, 9)], GSD, TILE,
                     contents={(0, 0): (10.0, 20.0, span, span), (0, 1): (span, 5.0, span + 30.0, 40.0)})
    got = part_bounds(plan, [(0, 0, 0, 1), (9, 9, 9, 9)], lambda x, y: (x, y))
    assert got == [(10.0, 5.0, span + 30.0, span), (9 * span, 9 * span, 10 * span, 10 * span)]
    shifted = part_bounds(plan, [(0, 0, 0, 1)], lambda x, y: (x + 100.0, 0.5 * y))
    assert shifted == [(110.0, 2.5, span + 130.0, span / 2)]


def test_overview_factors_follow_the_cog_driver():
    assert overview_factors(512, 300) == []
    assert overview_factors(1000, 200) == [2]
    assert overview_factors(5000, 800) == [2, 4, 8, 16]       # 5000 / 8 = 625 > 512, / 16 fits


def test_part_windows_sit_on_a_global_grid_aligned_to_every_overview():
    bounds = [(1000.0, 2000.0, 1100.0, 2050.0), (9000.0, 7000.0, 9100.0, 7100.0)]
    grid, windows = map_grid(bounds, 0.25)
    gt, width, height = grid.geotransform, grid.width, grid.height
    align = max([1, *overview_factors(width, height)])
    assert gt[0] % (align * 0.25) == 0 and gt[3] % (align * 0.25) == 0
    for (x0, y0, x1, y1), w in zip(bounds, windows):
        assert all(v % align == 0 for v in w)
        assert gt[0] + w.col0 * 0.25 <= x0 - 0.5 and gt[0] + w.col1 * 0.25 >= x1 + 0.5    # 2-px margin kept
        assert gt[3] - w.row1 * 0.25 <= y0 - 0.5 and gt[3] - w.row0 * 0.25 >= y1 + 0.5
    assert max(w.col1 for w in windows) == width and min(w.row0 for w in windows) == 0


def _tile_pixels(row: int, col: int) -> np.ndarray:
    """Deterministic RGBA content of tile (row, col): gradients and a disc, opaque but for a corner."""
    y, x = np.mgrid[0:TILE, 0:TILE]
    rgba = np.empty((TILE, TILE, 4), np.uint8)
    rgba[..., 0] = (x + 7 * col) % 256
    rgba[..., 1] = (y * 3 + 11 * row) % 256
    rgba[..., 2] = np.where((x - 64) ** 2 + (y - 50) ** 2 < 30 ** 2, 250, 40)
    rgba[..., 3] = 255
    rgba[:10, :15, 3] = 0
    return rgba


@pytest.fixture(scope="module")
def two_towns(tmp_path_factory):
    """Two groups of rendered tiles 17 tiles apart, mosaicked as the workflow does."""
    from pipeline25d.core.crs import horizontal_wkt

    d = tmp_path_factory.mktemp("towns")
    cells = [(r, c) for r in range(3) for c in range(3)] + [(r, c) for r in range(20, 22) for c in range(18, 20)]
    paths = []
    for r, c in cells:
        path = d / f"{r}_{c}.tif"
        span = TILE * GSD
        write_rgba_geotiff(path, _tile_pixels(r, c), Grid.north_up(c * span, (r + 1) * span, GSD, TILE, TILE),
                           horizontal_wkt(CRS))
        paths.append(str(path))
    build_mosaic(paths, d / "mosaic.vrt")
    plan = grid_plan(cells, GSD, TILE, CRS)
    return d, plan, cells


def _read(path, level=None):
    ds = gdal().Open(str(path))
    bands = [ds.GetRasterBand(b + 1) for b in range(4)]
    if level is not None:
        bands = [b.GetOverview(level) for b in bands]
    return ds.GetGeoTransform(), np.stack([b.ReadAsArray() for b in bands], axis=-1)


def _gcps(transform):
    """Observations whose true position is ``transform`` of the rendered one (a smooth warp)."""
    rng = np.random.default_rng(4)
    rows = []
    for k, (mx, my) in enumerate(rng.uniform([0, 0], [20 * TILE * GSD, 22 * TILE * GSD], (60, 2))):
        x, y = transform(mx, my)
        rows.append(Observation(str(k), x, y, 0.0, 0.0, 0.0, 0.0, "gcp" if k % 6 else "check", mx, my, 1))
    return rows


@pytest.mark.parametrize("method", ["none", "polynomial"])
def test_sparse_map_equals_the_map_warped_whole(two_towns, method, tmp_path):
    d, plan, cells = two_towns
    parts = tile_parts(cells)
    assert len(parts) == 2
    obs = _gcps(lambda x, y: (x + 0.3 + 1e-4 * y, y - 0.2 + 2e-4 * x))
    choice = {"method": method, "order": 1}
    dense_bounds = warp_to_cog(d / "mosaic.vrt", obs, choice, plan, tmp_path / "dense.tif")
    sparse_bounds = warp_to_cog(d / "mosaic.vrt", obs, choice, plan, tmp_path / "sparse.tif", parts=parts)
    assert len(dense_bounds) == 1 and len(sparse_bounds) == 2
    gt_d, dense = _read(tmp_path / "dense.tif")
    gt_s, sparse = _read(tmp_path / "sparse.tif")
    # both on the global gsd grid: the sparse map's pixel (i, j) is the dense map's (i + di, j + dj)
    dj, di = (gt_s[0] - gt_d[0]) / GSD, (gt_d[3] - gt_s[3]) / GSD
    assert dj == round(dj) and di == round(di)
    dj, di = int(dj), int(di)
    # compare where both exist
    r0, c0 = max(0, -di), max(0, -dj)
    r1, c1 = min(sparse.shape[0], dense.shape[0] - di), min(sparse.shape[1], dense.shape[1] - dj)
    a = sparse[r0:r1, c0:c1].astype(int)
    b = dense[r0 + di:r1 + di, c0 + dj:c1 + dj].astype(int)
    assert (b[..., 3] > 0).sum() > 0.9 * 13 * TILE * TILE          # the towns' pixels are in the common window
    if method == "none":
        np.testing.assert_array_equal(a, b)
    else:
        assert np.abs(a - b).max() <= 1                             # same warp, the parts' own approximations
    # nothing outside the parts, and the empty blocks are not stored
    ds = gdal().Open(str(tmp_path / "sparse.tif"))
    band = ds.GetRasterBand(1)
    nx, ny = -(-ds.RasterXSize // COG_BLOCK), -(-ds.RasterYSize // COG_BLOCK)
    stored = sum(bool(int(band.GetMetadataItem(f"BLOCK_OFFSET_{i}_{j}", "TIFF") or 0))
                 for i in range(nx) for j in range(ny))
    assert stored < 0.25 * nx * ny
    # overviews: the parts' own, the same as the COG driver's over the dense map
    levels = ds.GetRasterBand(1).GetOverviewCount()
    assert levels == len(overview_factors(ds.RasterXSize, ds.RasterYSize)) >= 2
    if method == "none":                        # both grids start on tile corners (multiples of 64 px)
        assert di % 4 == 0 and dj % 4 == 0
        for level, f in [(0, 2), (1, 4)]:
            a = _read(tmp_path / "sparse.tif", level)[1].astype(int)
            b = _read(tmp_path / "dense.tif", level)[1].astype(int)
            r0, c0 = max(0, -di // f), max(0, -dj // f)
            r1, c1 = min(a.shape[0], b.shape[0] - di // f), min(a.shape[1], b.shape[1] - dj // f)
            diff = np.abs(a[r0:r1, c0:c1] - b[r0 + di // f:r1 + di // f, c0 + dj // f:c1 + dj // f])
            assert diff.max() <= 1 and diff.mean() < 0.01, (f, diff.max(), diff.mean())


def test_web_tiles_of_a_sparse_map_are_gdal2tiles_cut_where_there_is_data(two_towns, tmp_path):
    """A sparse map is cut only where it holds data: the tiles gdal2tiles cuts over the whole
    map wherever a tile holds data, and no tile over the empty land between the towns. gdal2tiles
    cuts the whole map warped at once onto the pipeline's web-mercator grid (web.tile_grid: on its
    own grid gdal2tiles moves each tile by up to a pixel)."""
    import subprocess
    import sys

    from PIL import Image

    from pipeline25d.core.raster import gdal
    from pipeline25d.stages.tiles.blocks import mercator_args
    from pipeline25d.stages.tiles.web import tile_grid, tms

    d, plan, cells = two_towns
    warp_to_cog(d / "mosaic.vrt", [], {"method": "none", "order": 0}, plan, tmp_path / "map.tif",
                parts=tile_parts(cells))
    stats = tms(tmp_path / "map.tif", "auto", tmp_path / "ours", processes=2)
    grid, zooms = tile_grid(tmp_path / "map.tif", "auto")
    gdal().Warp(str(tmp_path / "whole.tif"), str(tmp_path / "map.tif"), options=mercator_args(
        1, ["-tr", repr(grid.transform.a), repr(-grid.transform.e), "-te", *map(repr, grid.bounds)]))
    subprocess.run([sys.executable, "-m", "osgeo_utils.gdal2tiles", "-q", "--xyz", "-w", "none", "-r", "average",
                    "-z", zooms, str(tmp_path / "whole.tif"), str(tmp_path / "whole")], check=True)
    whole = {p.relative_to(tmp_path / "whole") for p in (tmp_path / "whole").rglob("*.png")}
    ours = {p.relative_to(tmp_path / "ours") for p in (tmp_path / "ours").rglob("*.png")}
    assert ours <= whole and len(ours) < 0.5 * len(whole) and stats["web_tiles"] == len(ours)
    zooms = sorted({int(p.parts[0]) for p in whole})
    assert sorted({int(p.parts[0]) for p in ours}) == zooms and len(zooms) >= 4

    def rgba(path):
        with Image.open(path) as im:
            return np.asarray(im.convert("RGBA"), dtype=float)

    for rel in sorted(whole - ours):                         # skipped tiles hold nothing
        assert rgba(tmp_path / "whole" / rel)[..., 3].max() == 0, rel
    diffs = {z: [] for z in zooms}
    for rel in sorted(ours):
        diffs[int(rel.parts[0])].append(np.abs(rgba(tmp_path / "ours" / rel) - rgba(tmp_path / "whole" / rel)).mean())
    # gdal2tiles warps on its own: nearest-neighbour picks differ where its transform's approximation does
    every = [d for v in diffs.values() for d in v]
    assert np.mean(every) < 0.05 and max(every) < 1.0, (np.mean(every), max(every))


def test_gdal_block_cache_is_capped_in_process_and_for_the_tools(monkeypatch):
    """A job's memory must not grow with the map: GDAL's default cache (5 % of RAM) is capped."""
    from pipeline25d.core.raster import CACHE_MB, gdal, tool_env

    if "GDAL_CACHEMAX" not in os.environ:
        assert gdal().GetCacheMax() <= CACHE_MB << 20
    monkeypatch.delenv("GDAL_CACHEMAX", raising=False)
    assert tool_env()["GDAL_CACHEMAX"] == str(CACHE_MB)
    monkeypatch.setenv("GDAL_CACHEMAX", "1024")            # the user's own setting wins
    assert tool_env()["GDAL_CACHEMAX"] == "1024"
