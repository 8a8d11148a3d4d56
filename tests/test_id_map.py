"""The id map (stages.maps.ids) against its map and an analytic scene: discs of known ids in
rendered tiles, warped by a known affine through GCPs; patched where a tile changed."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import grid_plan

from pipeline25d.core.crs import horizontal_wkt
from pipeline25d.core.geotiff import write_geotiff, write_rgba_geotiff
from pipeline25d.core.grid import Grid
from pipeline25d.core.raster import gdal
from pipeline25d.stages.gcps import OBSERVATION_FIELDS, write_csv
from pipeline25d.stages.maps import patch as map_patch
from pipeline25d.stages.maps.ids import conform, id_map
from pipeline25d.stages.maps.mosaic_sources import build_mosaic
from pipeline25d.stages.maps.warp import warp_to_cog
from pipeline25d.stages.records import Observation

GSD, TILE, CRS = 0.5, 128, "EPSG:25832"
SPAN = TILE * GSD


def warp_xy(x, y):
    """The true position of a rendered one: a rotation by ~0.6° and a shift (m)."""
    return x + 0.01 * y + 0.7, y - 0.01 * x - 0.4


def discs(cells) -> list[tuple[float, float, float, int]]:
    """(x, y, radius, id): one disc per tile, off the pixel grid, ids across uint32."""
    out = []
    for r, c in cells:
        k = 37 * r + c + 1
        out.append((c * SPAN + 20.3 + (k % 5) * 3.1, -(r * SPAN) - 23.7 - (k % 3) * 4.3, 9.0 + k % 4,
                    (k * 2_654_435_761) % (1 << 32) or 1))
    return out


def write_tile(d, row, col, objects) -> None:
    """The tile's RGBA (opaque in its discs, a faint 1 px rim: alpha 1 or 60) and its ids, where alpha > 0."""
    grid = Grid.north_up(col * SPAN, -row * SPAN, GSD, TILE, TILE)
    x, y = grid.cell_centres()
    rgba = np.zeros((TILE, TILE, 4), np.uint8)
    ids = np.zeros((TILE, TILE), np.uint32)
    for cx, cy, radius, oid in objects:
        dist = np.hypot(x - cx, y - cy)
        rim = (dist >= radius) & (dist < radius + GSD)
        inside = dist < radius
        rgba[inside | rim, :3] = (oid % 251, oid % 241, 90)
        rgba[inside, 3] = 255
        rgba[rim, 3] = np.where((x[rim] + y[rim]) % 2 < 1, 1, 60)
        ids[inside | rim] = oid
    write_rgba_geotiff(d / f"{row}_{col}.tif", rgba, grid, horizontal_wkt(CRS))
    write_geotiff(d / f"{row}_{col}.ids.tif", ids, grid, horizontal_wkt(CRS), "UInt32", ("TILED=YES",), nodata=0)


def scene(tmp_path, cells, seed_cells=()):
    """Tiles of ``cells`` in tmp_path/tiles (those in ``seed_cells`` with their discs moved), their mosaics
    and GCPs of :func:`warp_xy`."""
    d = tmp_path / "tiles"
    d.mkdir(exist_ok=True)
    for (r, c), disc in zip(cells, discs(cells)):
        moved = (disc[0] + 6.0, disc[1] - 2.0, disc[2], disc[3] + 1) if (r, c) in seed_cells else disc
        write_tile(d, r, c, [moved])
    build_mosaic(sorted(str(p) for p in d.glob("*_*.tif") if ".ids" not in p.name), d / "mosaic.vrt")
    build_mosaic(sorted(str(p) for p in d.glob("*_*.ids.tif")), d / "ids.vrt")
    rng = np.random.default_rng(3)
    (c0, r0), (c1, r1) = np.min(cells, axis=0)[::-1], np.max(cells, axis=0)[::-1]
    obs = [Observation(str(k), *warp_xy(mx, my), 0.0, 0.0, 0.0, 0.0, "gcp", mx, my, 1)
           for k, (mx, my) in enumerate(rng.uniform([c0 * SPAN, -(r1 + 1) * SPAN], [(c1 + 1) * SPAN, -r0 * SPAN],
                                                     (30, 2)))]
    write_csv(d / "gcps.csv", obs, OBSERVATION_FIELDS)
    return d, obs


def make_maps(tmp_path, d, obs, cells, method, name="a", work=True):
    """The map (warp_to_cog, as the warp job) and its id map; the id map's stats."""
    from pipeline25d.stages.maps.parts import tile_parts

    plan = grid_plan(cells, GSD, TILE, CRS, {(r, c): (c * SPAN, -(r + 1) * SPAN, (c + 1) * SPAN, -r * SPAN)
                                             for r, c in cells})
    choice = {"method": method, "order": 1 if method == "polynomial" else 0}      # (tps: no order)
    parts = warp_to_cog(d / "mosaic.vrt", obs, choice, plan, tmp_path / f"{name}.tif",
                        parts=tile_parts((t.row, t.col) for t in plan.tiles),
                        work_dir=tmp_path / f"{name}.kept" if work else None)
    (tmp_path / f"{name}.json").write_text(json.dumps({**choice, "parts": parts}))
    return id_map(d / "ids.vrt", d / "mosaic.vrt", d / "gcps.csv", tmp_path / f"{name}.json", tmp_path / f"{name}.tif",
                  tmp_path / f"{name}.ids.tif", tmp_path / f"{name}.ids.json",
                  work_dir=tmp_path / f"{name}.ids.kept" if work else None)


def read(path, band=1) -> tuple[Grid, np.ndarray]:
    ds = gdal().Open(str(path))
    return Grid.of_dataset(ds), ds.GetRasterBand(band).ReadAsArray()


def check_against_map(tmp_path, name, cells, stats, warped: bool) -> None:
    """Counted apart from the job: every opaque map pixel has an id, no transparent one has; each
    disc's centre, moved by the warp, carries the disc's id; the same grid as the map."""
    grid, alpha = read(tmp_path / f"{name}.tif", 4)
    ids_grid, ids = read(tmp_path / f"{name}.ids.tif")
    ds = gdal().Open(str(tmp_path / f"{name}.ids.tif"))
    assert ds.GetRasterBand(1).DataType == gdal().GDT_UInt32 and ds.GetRasterBand(1).GetNoDataValue() == 0
    assert ids_grid == grid and ds.GetProjection() == gdal().Open(str(tmp_path / f"{name}.tif")).GetProjection()
    assert ((alpha > 0) & (ids == 0)).sum() == 0 and ((alpha == 0) & (ids != 0)).sum() == 0
    assert stats["opaque_without_id"] == stats["transparent_with_id"] == 0
    assert stats["opaque_px"] == int((alpha > 0).sum()) > 0
    for cx, cy, _, oid in discs(cells):
        x, y = warp_xy(cx, cy) if warped else (cx, cy)
        col, row = grid.colrow(x, y)
        assert ids[int(row), int(col)] == oid


@pytest.mark.parametrize("method", ["none", "polynomial", "tps"])
def test_an_id_map_agrees_with_its_map_and_shows_each_object_where_the_warp_puts_it(tmp_path, method, monkeypatch):
    monkeypatch.setattr(map_patch, "BLOCK_PX", 256)
    monkeypatch.setattr("pipeline25d.stages.maps.ids.BLOCK_PX", 256)
    cells = [(r, c) for r in range(4) for c in range(5)]
    d, obs = scene(tmp_path, cells)
    stats = make_maps(tmp_path, d, obs, cells, method)
    check_against_map(tmp_path, "a", cells, stats, method != "none")
    assert stats["parts"] == 1 and stats["full"] and stats["blocks"] >= 6
    # nearest ids agree with the bilinear alpha as warped, faint (alpha 1) rims included: nothing to fix
    assert stats["filled"] == stats["cleared"] == 0
    assert 0 < stats["ids_bytes"] and stats["map_bytes"] == (tmp_path / "a.tif").stat().st_size


def test_a_changed_tile_redoes_only_the_id_blocks_it_reaches_and_equals_a_fresh_id_map(tmp_path, monkeypatch):
    monkeypatch.setattr(map_patch, "BLOCK_PX", 256)
    monkeypatch.setattr("pipeline25d.stages.maps.ids.BLOCK_PX", 256)
    cells = [(r, c) for r in range(4) for c in range(6)]
    d, obs = scene(tmp_path, cells)
    first = make_maps(tmp_path, d, obs, cells, "polynomial")
    before = read(tmp_path / "a.ids.tif")[1]
    kept = tmp_path / "a.ids.kept" / "ids.tif"
    kept_before = read(kept)[1]
    d, obs = scene(tmp_path, cells, seed_cells={(1, 4)})
    patch = make_maps(tmp_path, d, obs, cells, "polynomial")
    assert first["full"] and not patch["full"] and patch["mosaic_cells_changed"] == 1
    assert 1 <= patch["blocks_redone"] <= 4 < patch["blocks"]
    fresh = make_maps(tmp_path, d, obs, cells, "polynomial", name="b", work=False)
    assert fresh["full"] and (tmp_path / "a.ids.tif").read_bytes() == (tmp_path / "b.ids.tif").read_bytes()
    check_against_map(tmp_path, "a", [c for c in cells if c != (1, 4)], patch, True)
    # the kept blocks the change did not reach are the same pixels; the moved disc's tile differs
    after, size = read(kept)[1], 256
    changed = {(c // size, r // size) for r, c in zip(*np.nonzero(after != kept_before))}
    assert changed and len(changed) <= patch["blocks_redone"]
    assert (before != read(tmp_path / "a.ids.tif")[1]).any()


def test_a_sparse_map_has_its_ids_part_by_part(tmp_path):
    cells = [(r, c) for r in range(2) for c in range(2)] + [(r, c) for r in range(9, 11) for c in range(12, 14)]
    d, obs = scene(tmp_path, cells)
    stats = make_maps(tmp_path, d, obs, cells, "polynomial")
    assert stats["parts"] == 2
    check_against_map(tmp_path, "a", cells, stats, True)
    ds = gdal().Open(str(tmp_path / "a.ids.tif"))
    assert ds.GetMetadata("IMAGE_STRUCTURE").get("LAYOUT") == "COG"
    assert ds.GetRasterBand(1).GetOverviewCount() >= 1


def test_conform_clears_ids_under_transparency_and_fills_opaque_holes_from_the_nearest_id():
    ids = np.array([[0, 0, 0, 0], [0, 5, 5, 0], [0, 5, 7, 0], [9, 0, 0, 0]], np.uint32)
    alpha = np.array([[0, 9, 0, 0], [0, 255, 255, 0], [0, 255, 255, 3], [0, 0, 0, 0]], np.uint8)
    out, filled, cleared = conform(ids, alpha)
    assert out[0, 1] == 5 and out[2, 3] == 7 and out[3, 0] == 0
    assert filled.sum() == 2 and cleared.sum() == 1 and np.array_equal(out > 0, alpha > 0)


def test_id_blocks_where_the_map_stores_nothing_are_not_made_and_the_id_map_is_the_same(tmp_path, monkeypatch):
    """An 8 x 8 tile map with a 4 x 4 tile hole (512 px: one of the COG's blocks, which it does not
    store; one part; no warp, so the hole is four whole id blocks): those blocks are not made, and
    the id map is byte for byte the one made block by block."""
    from pipeline25d.stages.maps import ids as map_ids

    monkeypatch.setattr(map_patch, "BLOCK_PX", 256)
    monkeypatch.setattr(map_ids, "BLOCK_PX", 256)
    cells = [(r, c) for r in range(8) for c in range(8) if not (r < 4 and c >= 4)]
    d, obs = scene(tmp_path, cells)
    made = []
    make = map_ids._Blocks.make
    monkeypatch.setattr(map_ids._Blocks, "make", lambda self, win: (made.append(win), make(self, win))[1])
    stats = make_maps(tmp_path, d, obs, cells, "none")
    assert stats["parts"] == 1 and stats["blocks"] == 16 and len(made) == 12
    check_against_map(tmp_path, "a", cells, stats, False)
    monkeypatch.setattr(map_ids._Blocks, "nothing_drawn", lambda self, win: False)
    every = make_maps(tmp_path, d, obs, cells, "none", name="b")
    assert len(made) == 12 + 16 and every["filled"] == stats["filled"] and every["cleared"] == stats["cleared"]
    assert (tmp_path / "a.ids.tif").read_bytes() == (tmp_path / "b.ids.tif").read_bytes()
