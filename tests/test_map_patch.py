"""A warped map kept and patched: an update warps only the blocks a changed tile reaches and
equals, byte for byte, a map warped from scratch; block-wise warping matches one gdalwarp."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest
from conftest import grid_plan

from pipeline25d.core.crs import horizontal_wkt
from pipeline25d.core.geotiff import write_rgba_geotiff
from pipeline25d.core.grid import Grid
from pipeline25d.core.raster import gdal
from pipeline25d.stages.maps import patch as map_patch
from pipeline25d.stages.maps.mosaic_sources import build_mosaic
from pipeline25d.stages.maps.patch import blank, block_window, patched_map
from pipeline25d.stages.maps.warp import gdal_gcps, raster_grid, warp_to_cog
from pipeline25d.stages.records import Observation

GSD, TILE, ROWS, COLS = 0.5, 128, 10, 12
CRS = "EPSG:25832"
BLOCK = 256                     # small blocks, so that this small map has many
CHANGED = (4, 5)                # the tile replaced


def _pixels(row: int, col: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(1000 * seed + 31 * row + col)
    rgba = rng.integers(0, 256, (TILE, TILE, 4), dtype=np.uint8)
    rgba[..., 3] = 255
    return rgba


def _write_tile(d, row, col, seed=0) -> str:
    path = d / f"{row}_{col}.tif"
    span = TILE * GSD
    write_rgba_geotiff(path, _pixels(row, col, seed), Grid.north_up(col * span, (ROWS - row) * span, GSD, TILE, TILE),
                       horizontal_wkt(CRS))
    return str(path)


def _observations(shift: float = 0.0) -> list[Observation]:
    """GCPs of a smooth warp: a rotation by ~0.6° and a shift (metres)."""
    rng = np.random.default_rng(7)
    rows = []
    for k, (mx, my) in enumerate(rng.uniform([0, 0], [COLS * TILE * GSD, ROWS * TILE * GSD], (40, 2))):
        rows.append(Observation(str(k), mx + 0.01 * my + 0.7 + shift, my - 0.01 * mx - 0.4, 0.0, 0.0, 0.0, 0.0, "gcp",
                                mx, my, 1))
    return rows


def _source(d, obs) -> tuple[str, str]:
    """The mosaic of the tiles in ``d``, and a VRT of it with GCPs ``obs``."""
    mosaic = d / "mosaic.vrt"
    build_mosaic([str(p) for p in sorted(d.glob("*_*.tif"))], mosaic)
    src = d / "gcps.vrt"
    gdal().Translate(str(src), str(mosaic), format="VRT", outputSRS=horizontal_wkt(CRS),
                     GCPs=gdal_gcps(obs, raster_grid(mosaic)))
    return str(mosaic), str(src)


def _tiles(tmp_path, monkeypatch):
    """ROWS x COLS tiles in tmp_path/tiles, and small map blocks."""
    monkeypatch.setattr(map_patch, "BLOCK_PX", BLOCK)
    d = tmp_path / "tiles"
    d.mkdir()
    for r in range(ROWS):
        for c in range(COLS):
            _write_tile(d, r, c)
    return d


def _pixels_of(path) -> np.ndarray:
    return gdal().Open(str(path)).ReadAsArray().astype(int)


def test_a_patch_warps_only_the_blocks_a_changed_tile_reaches_and_equals_a_fresh_warp(tmp_path, monkeypatch):
    d = _tiles(tmp_path, monkeypatch)
    choice, crs = {"method": "polynomial", "order": 1}, horizontal_wkt(CRS)
    mosaic, src = _source(d, _observations())
    kept, first = patched_map(mosaic, src, choice, crs, GSD, tmp_path / "kept")
    assert first["full"] and first["blocks_redone"] == first["blocks"] >= 30
    before = _pixels_of(kept)

    # block by block, as one gdalwarp of the whole map does (up to its own approximation)
    whole = gdal().Warp(str(tmp_path / "whole.tif"), src, **map_patch.warp_options(choice, crs, GSD))
    assert whole.GetGeoTransform() == gdal().Open(str(kept)).GetGeoTransform()
    diff = np.abs(whole.ReadAsArray().astype(int) - before)
    whole = None
    assert diff.mean() < 0.05 and np.percentile(diff, 99.9) <= 8, (diff.mean(), diff.max())

    _write_tile(d, *CHANGED, seed=1)
    mosaic, src = _source(d, _observations())
    kept, patch = patched_map(mosaic, src, choice, crs, GSD, tmp_path / "kept")
    assert not patch["full"] and patch["mosaic_cells_changed"] == 1        # the tile is one 128 px square
    assert 1 <= patch["blocks_redone"] <= 4 < first["blocks"]
    after = _pixels_of(kept)
    _, fresh = patched_map(mosaic, src, choice, crs, GSD, tmp_path / "fresh")
    assert fresh["full"]
    np.testing.assert_array_equal(after, _pixels_of(tmp_path / "fresh" / "map.tif"))
    for level in range(2):                                                 # and their overviews
        np.testing.assert_array_equal(_overview(kept, level), _overview(tmp_path / "fresh" / "map.tif", level))

    # the blocks whose pixels changed lie where the warp takes the tile, and were all warped again
    width, height = after.shape[2], after.shape[1]
    changed = {(bx, by) for bx in range(-(-width // BLOCK)) for by in range(-(-height // BLOCK))
               if (before[:, (w := block_window(bx, by, width, height, BLOCK)).row0:w.row1, w.col0:w.col1]
                   != after[:, w.row0:w.row1, w.col0:w.col1]).any()}
    assert changed and len(changed) <= patch["blocks_redone"]
    gt = gdal().Open(str(kept)).GetGeoTransform()
    r, c = CHANGED
    x, y = (c + 0.5) * TILE * GSD, (ROWS - r - 0.5) * TILE * GSD          # the tile's centre, then warped
    x, y = x + 0.01 * y + 0.7, y - 0.01 * x - 0.4
    assert (int((x - gt[0]) / gt[1]) // BLOCK, int((y - gt[3]) / gt[5]) // BLOCK) in changed

    # nothing changed: nothing warped; other GCPs: everything
    _, same = patched_map(mosaic, src, choice, crs, GSD, tmp_path / "kept")
    assert not same["full"] and same["blocks_redone"] == 0
    _, moved = patched_map(*_source(d, _observations(shift=1.0)), choice, crs, GSD, tmp_path / "kept")
    assert moved["full"] and moved["blocks_redone"] == moved["blocks"]


def _overview(path, level: int) -> np.ndarray:
    ds = gdal().Open(str(path))
    return np.stack([ds.GetRasterBand(b + 1).GetOverview(level).ReadAsArray() for b in range(ds.RasterCount)])


def test_an_unwarped_map_is_patched_in_the_blocks_its_changed_tile_lies_in(tmp_path, monkeypatch):
    """No warp: the map is the mosaic; a changed tile redoes exactly the block it lies in, and the
    kept map equals the mosaic, its block-built overviews the COG driver's (to rounding)."""
    d = _tiles(tmp_path, monkeypatch)
    none, crs = {"method": "none", "order": 0}, horizontal_wkt(CRS)
    mosaic, src = _source(d, _observations())
    patched_map(mosaic, src, none, crs, GSD, tmp_path / "kept")
    _write_tile(d, 3, 5, seed=1)                   # rows 384..511, columns 640..767: blocks (2, 1)
    mosaic, src = _source(d, _observations())
    kept, patch = patched_map(mosaic, src, none, crs, GSD, tmp_path / "kept")
    assert not patch["full"] and patch["blocks_redone"] == 1 and patch["mosaic_cells_changed"] == 1
    np.testing.assert_array_equal(_pixels_of(kept), _pixels_of(mosaic))
    gdal().Translate(str(tmp_path / "ref.tif"), mosaic, format="COG",   # not kept: closed, so written, at once
                     creationOptions=["OVERVIEWS=AUTO", "RESAMPLING=AVERAGE", "COMPRESS=DEFLATE"])
    ref = gdal().Open(str(tmp_path / "ref.tif"))
    levels = ref.GetRasterBand(1).GetOverviewCount()
    ref = None
    assert levels == 2
    for level in range(levels):
        diff = np.abs(_overview(kept, level).astype(int) - _overview(tmp_path / "ref.tif", level))
        # averaging rounds once per level or once overall: at most one grey level apart
        assert diff.max() <= 1 and diff.mean() < 0.25, (level, diff.max(), diff.mean())


def test_the_cog_of_a_patched_warp_equals_a_fresh_one_byte_for_byte(tmp_path, monkeypatch):
    monkeypatch.setattr(map_patch, "BLOCK_PX", BLOCK)
    d = tmp_path / "tiles"
    d.mkdir()
    cells = [(r, c) for r in range(4) for c in range(5)]
    for r, c in cells:
        _write_tile(d, r, c)
    plan = grid_plan(cells, GSD, TILE, CRS)
    choice, obs = {"method": "polynomial", "order": 1}, _observations()
    build_mosaic([str(p) for p in sorted(d.glob("*_*.tif"))], d / "mosaic.vrt")
    warp_to_cog(d / "mosaic.vrt", obs, choice, plan, tmp_path / "a.tif", work_dir=tmp_path / "kept")
    _write_tile(d, 1, 2, seed=1)
    warp_to_cog(d / "mosaic.vrt", obs, choice, plan, tmp_path / "a.tif", work_dir=tmp_path / "kept")
    warp_to_cog(d / "mosaic.vrt", obs, choice, plan, tmp_path / "b.tif")            # from scratch, no kept warp
    assert (tmp_path / "a.tif").read_bytes() == (tmp_path / "b.tif").read_bytes()
    assert not (tmp_path / "b.blocks").exists() and not list(tmp_path.glob(".b.tif*"))
    # a map that needs no warp is kept too: the same, one block patched
    none = {"method": "none", "order": 0}
    warp_to_cog(d / "mosaic.vrt", obs, none, plan, tmp_path / "a.tif", work_dir=tmp_path / "kept")
    _write_tile(d, 2, 3, seed=2)
    warp_to_cog(d / "mosaic.vrt", obs, none, plan, tmp_path / "a.tif", work_dir=tmp_path / "kept")
    warp_to_cog(d / "mosaic.vrt", obs, none, plan, tmp_path / "b.tif")
    assert (tmp_path / "a.tif").read_bytes() == (tmp_path / "b.tif").read_bytes()
    shutil.rmtree(d)


def test_the_digests_taken_from_the_blocks_are_map_cells_own(tmp_path, monkeypatch):
    """The map's digests, taken from each block as it is made, equal map_cells read from the kept map,
    and, for a copied map made whole, the mosaic's (so its warp reads the mosaic once): whole, warped,
    and after a patch that replaced one block's. The note a lossless COG gets equals map_cells of the
    COG and is refused once the COG is another version of it."""
    from pipeline25d.core.raster import map_cells, noted_cells

    monkeypatch.setattr(map_patch, "BLOCK_PX", BLOCK)
    d = tmp_path / "tiles"
    d.mkdir()
    cells = [(r, c) for r in range(5) for c in range(6) if (r, c) != (2, 2)]      # a hole
    for r, c in cells:
        _write_tile(d, r, c)
    rgba = _pixels(0, 0, seed=3)
    rgba[40:90, 10:128, 3] = 0                                                   # a tile half see-through
    write_rgba_geotiff(d / "0_0.tif", rgba, Grid.north_up(0, ROWS * TILE * GSD, GSD, TILE, TILE), horizontal_wkt(CRS))
    crs = horizontal_wkt(CRS)
    for choice in ({"method": "none", "order": 0}, {"method": "polynomial", "order": 1}):
        work = tmp_path / choice["method"]
        mosaic, src = _source(d, _observations())
        memo: dict = {}
        kept, made = patched_map(mosaic, src, choice, crs, GSD, work, memo)
        grid, own = made["map_cells"]
        assert made["full"] and (grid, own) == map_cells(kept) and len(own) > 20
        mosaic_cells = map_cells(mosaic)
        assert memo[(mosaic, 128)] == mosaic_cells and map_patch.read_state(work)["cells"] == mosaic_cells[1]
        if choice["method"] == "none":
            assert own == mosaic_cells[1]
        _write_tile(d, 3, 4, seed=4)
        mosaic, src = _source(d, _observations())
        kept, patch = patched_map(mosaic, src, choice, crs, GSD, work)
        assert not patch["full"] and 1 <= patch["blocks_redone"] < patch["blocks"]
        assert patch["map_cells"] == map_cells(kept) and patch["map_cells"][1] != own
        _write_tile(d, 3, 4)

    plan = grid_plan(cells, GSD, TILE, CRS)
    note = tmp_path / "note.json"
    warp_to_cog(d / "mosaic.vrt", _observations(), {"method": "none", "order": 0}, plan, tmp_path / "a.tif",
                work_dir=tmp_path / "kept", cells_note=note)
    assert noted_cells(note, tmp_path / "a.tif") == map_cells(tmp_path / "a.tif")
    os.utime(tmp_path / "a.tif")                                                  # touched (Snakemake does): the same
    assert noted_cells(note, tmp_path / "a.tif") == map_cells(tmp_path / "a.tif")
    ds = gdal().Open(str(tmp_path / "a.tif"), 1)                                   # another version of the file
    ds.SetMetadataItem("edited", "yes")
    ds = None
    assert noted_cells(note, tmp_path / "a.tif") is None and noted_cells(None, tmp_path / "a.tif") is None
    warp_to_cog(d / "mosaic.vrt", _observations(), {"method": "none", "order": 0}, plan, tmp_path / "a.tif",
                compression="webp", work_dir=tmp_path / "kept", cells_note=note)
    assert not note.exists()                                                       # lossy: the COG is not the map


def test_blocks_made_by_worker_processes_give_the_same_map_as_made_here(tmp_path, monkeypatch):
    """The blocks of a map made by two forked workers (the last map of a run, with a core idle)
    and here, one after another: the same pixels and overviews, warped or copied, the same COG,
    the same digests. GDAL's warp threads are in this process, not in a forked one: the
    workers warp on one thread each, and the warp here (its thread pool started) must not hang them."""
    d = _tiles(tmp_path, monkeypatch)
    crs = horizontal_wkt(CRS)
    mosaic, src = _source(d, _observations())
    cells = [(r, c) for r in range(ROWS) for c in range(COLS)]
    plan = grid_plan(cells, GSD, TILE, CRS)
    gdal().Warp("", src, format="MEM", **map_patch.warp_options({"method": "polynomial", "order": 1}, crs, GSD))
    for choice in ({"method": "polynomial", "order": 1}, {"method": "none", "order": 0}):
        made = {}
        for workers in (1, 2):
            monkeypatch.setattr(map_patch, "job_workers", lambda threads, n=workers: n)
            out = tmp_path / f"{choice['method']}{workers}"
            kept, stats = patched_map(mosaic, src, choice, crs, GSD, out / "kept")
            assert stats["full"] and stats["blocks_redone"] == stats["blocks"] >= 30
            warp_to_cog(mosaic, _observations(), choice, plan, out / "map.tif", work_dir=out / "cog")
            made[workers] = (_pixels_of(kept), [_overview(kept, k) for k in range(2)], stats["map_cells"],
                             (out / "map.tif").read_bytes())
        np.testing.assert_array_equal(made[1][0], made[2][0])
        for a, b in zip(made[1][1], made[2][1]):
            np.testing.assert_array_equal(a, b)
        assert made[1][2] == made[2][2] and made[1][3] == made[2][3]
        assert made[1][0][3].any() and len(made[1][3]) > 10_000


@pytest.mark.parametrize("workers", [1, 2])
def test_blank_blocks_of_a_new_map_are_not_made_and_read_as_the_zeros_they_hold(tmp_path, monkeypatch, workers):
    """Drawn tiles in two corners only (a sparse city): the map's blocks over nothing get no
    overviews and no writes (made here or by worker processes), the kept file stores none of them
    (GDAL: data coverage EMPTY there), and it reads pixel for pixel, overviews too, as the map
    made writing every block. A later patch that blanks a drawn tile writes its block's zeros
    (the kept file had pixels there)."""
    monkeypatch.setattr(map_patch, "BLOCK_PX", BLOCK)
    monkeypatch.setattr(map_patch, "job_workers", lambda threads: workers)
    d = tmp_path / "tiles"
    d.mkdir()
    drawn = {(0, 0), (0, 1), (ROWS - 1, COLS - 1)}
    for r in range(ROWS):
        for c in range(COLS):
            path = _write_tile(d, r, c)
            if (r, c) not in drawn:
                write_rgba_geotiff(path, np.zeros((TILE, TILE, 4), np.uint8),
                                   Grid.of_dataset(gdal().Open(path)), horizontal_wkt(CRS))
    none, crs = {"method": "none", "order": 0}, horizontal_wkt(CRS)
    mosaic, src = _source(d, _observations())
    writes = []
    write_levels = map_patch.write_levels            # each block's levels are written here, whoever made them
    monkeypatch.setattr(map_patch, "write_levels", lambda kept, levels, win, *a: (writes.append(win),
                                                                                write_levels(kept, levels, win, *a)))
    kept, made = patched_map(mosaic, src, none, crs, GSD, tmp_path / "kept")
    drawn_blocks = len(writes)
    monkeypatch.setattr(map_patch, "blank", lambda block: False)
    every, _ = patched_map(mosaic, src, none, crs, GSD, tmp_path / "every")
    assert made["blocks"] == len(writes) - drawn_blocks > drawn_blocks == 2      # tiles (0, 0), (0, 1): one block
    np.testing.assert_array_equal(_pixels_of(kept), _pixels_of(every))
    for level in range(2):
        np.testing.assert_array_equal(_overview(kept, level), _overview(every, level))

    def coverage(path, col: int, row: int) -> int:
        ds = gdal().Open(str(path))                     # held while its band is asked
        return ds.GetRasterBand(1).GetDataCoverageStatus(col, row, BLOCK, BLOCK)[0]

    assert coverage(kept, 2 * BLOCK, 2 * BLOCK) == gdal().GDAL_DATA_COVERAGE_STATUS_EMPTY    # between the corners
    assert coverage(kept, 0, 0) & gdal().GDAL_DATA_COVERAGE_STATUS_DATA
    monkeypatch.setattr(map_patch, "blank", blank)
    write_rgba_geotiff(d / "0_0.tif", np.zeros((TILE, TILE, 4), np.uint8),
                       Grid.of_dataset(gdal().Open(str(d / "0_0.tif"))), horizontal_wkt(CRS))
    mosaic, src = _source(d, _observations())
    kept, patch = patched_map(mosaic, src, none, crs, GSD, tmp_path / "kept")
    assert not patch["full"] and patch["blocks_redone"] == 1
    np.testing.assert_array_equal(_pixels_of(kept), _pixels_of(mosaic))


@pytest.mark.parametrize("method, order", [("none", 0), ("polynomial", 1)])
def test_blocks_no_rendered_tile_reaches_are_not_made(tmp_path, monkeypatch, method, order):
    """Tiles rendered in two corners only (the mosaic has no others): a new map makes only the blocks
    its tiles reach (their squares of data through the warp, or the tiles' own windows where it is
    copied), and reads pixel for pixel, overviews too, as the map that makes every block."""
    monkeypatch.setattr(map_patch, "BLOCK_PX", BLOCK)
    d = tmp_path / "tiles"
    d.mkdir()
    for r, c in ((0, 0), (0, 1), (ROWS - 1, COLS - 1)):
        _write_tile(d, r, c)
    choice, crs = {"method": method, "order": order}, horizontal_wkt(CRS)
    mosaic, src = _source(d, _observations())
    kept, stats = patched_map(mosaic, src, choice, crs, GSD, tmp_path / "kept")
    ds = gdal().Open(str(kept))
    nx, ny = -(-ds.RasterXSize // BLOCK), -(-ds.RasterYSize // BLOCK)
    ds = None
    monkeypatch.setattr(map_patch, "blocks_reached", lambda *a: {(bx, by) for bx in range(nx) for by in range(ny)})
    every, all_stats = patched_map(mosaic, src, choice, crs, GSD, tmp_path / "every")
    assert all_stats["blocks_redone"] == all_stats["blocks"] == stats["blocks"] == nx * ny
    assert 2 <= stats["blocks_redone"] <= nx * ny // 3          # the corners' blocks, not the land between
    np.testing.assert_array_equal(_pixels_of(kept), _pixels_of(every))
    for level in range(2):
        np.testing.assert_array_equal(_overview(kept, level), _overview(every, level))
    assert _pixels_of(kept)[3].any()
