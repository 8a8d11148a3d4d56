"""The id web tiles (pipeline25d.stages.tiles.ids): a map and its id raster of known rectangles cut
into XYZ pyramids; every id tile pixel against the id raster looked up at the pixel's own centre
(reprojected independently), the tile set against the map's, the 2 x 2 mode of the zooms above,
and an update that rewrites only the id tiles a changed rectangle reaches."""

from __future__ import annotations

import os
import zlib

import numpy as np

from pipeline25d.core.crs import horizontal_wkt, transform_points
from pipeline25d.core.geotiff import write_geotiff, write_rgba_geotiff
from pipeline25d.core.grid import Grid
from pipeline25d.stages.tiles import ids as id_tiles
from pipeline25d.stages.tiles.blocks import WEB_MERCATOR
from pipeline25d.stages.tiles.web import tms

GRID = Grid.north_up(691000.0, 5334000.0, 0.5, 700, 500)
WORLD = 2 * 20037508.342789244
# (row0, col0, row1, col1, id): ground first, buildings on it; the rest transparent
RECTS = [(40, 30, 470, 660, 7 << 22 | 1), (100, 80, 180, 200, 7 << 22 | 2), (250, 300, 420, 390, 3 << 22 | 5),
         (60, 450, 140, 620, 7 << 22 | 4194303)]


def scene(tmp_path, rects=RECTS, name=""):
    """(map, id raster) of ``rects`` on GRID: the map opaque exactly where an id is."""
    ids = np.zeros((GRID.height, GRID.width), np.uint32)
    for r0, c0, r1, c1, v in rects:
        ids[r0:r1, c0:c1] = v
    rgba = np.zeros((*ids.shape, 4), np.uint8)
    rgba[..., 0] = (ids * 37 % 251).astype(np.uint8)
    rgba[..., 1] = (ids >> 22).astype(np.uint8)
    rgba[..., 3] = np.where(ids > 0, 255, 0)
    wkt = horizontal_wkt("EPSG:25832")
    write_rgba_geotiff(tmp_path / f"map{name}.tif", rgba, GRID, wkt)
    write_geotiff(tmp_path / f"map{name}.ids.tif", ids, GRID, wkt, "UInt32", ["TILED=YES", "COMPRESS=ZSTD"],
                  nodata=0)
    return tmp_path / f"map{name}.tif", tmp_path / f"map{name}.ids.tif", ids


def tiles_of(root, ext):
    return {str(p.relative_to(root).with_suffix("")): p for p in sorted(root.rglob(f"*.{ext}"))}


def centres_lookup(ids: np.ndarray, z: int, x: int, y: int) -> tuple[np.ndarray, np.ndarray]:
    """The id raster at every pixel centre of web tile (z, x, y) (an independent float64 reprojection),
    and the ids within two id-raster pixels of it ((256, 256, 25): the tile was resampled twice by
    nearest neighbour, to web mercator, then to the tile, whose pixel here is 1.6 of the raster's:
    together they may move a pixel by up to about 1.3 raster pixels)."""
    span = WORLD / 2 ** z
    j, i = np.mgrid[0:256, 0:256] + 0.5
    mx, my = x * span - WORLD / 2 + i * span / 256, WORLD / 2 - y * span - j * span / 256
    pts = transform_points(np.column_stack([mx.ravel(), my.ravel(), np.zeros(mx.size)]), WEB_MERCATOR,
                           horizontal_wkt("EPSG:25832"))
    col, row = (pts[:, 0] - GRID.transform.c) / 0.5, (GRID.transform.f - pts[:, 1]) / 0.5
    inside = (col >= 0) & (col < GRID.width) & (row >= 0) & (row < GRID.height)
    padded = np.pad(ids, 3)
    c, r = np.clip(np.floor(col).astype(int), -1, GRID.width), np.clip(np.floor(row).astype(int), -1, GRID.height)
    want = np.where(inside, padded[r + 3, c + 3], 0).reshape(256, 256)
    near = np.stack([padded[r + 3 + dr, c + 3 + dc] for dr in range(-2, 3) for dc in range(-2, 3)], axis=-1)
    return want, near.reshape(256, 256, 25)


def test_id_tiles_hold_the_id_under_every_pixel_centre_and_lie_where_the_map_tiles_are(tmp_path):
    cog, ids_tif, ids = scene(tmp_path)
    tms(cog, "auto", tmp_path / "map", tile_format="png")
    stats = tms(ids_tif, "auto", tmp_path / "ids", tile_format="ids")
    got, maps = tiles_of(tmp_path / "ids", id_tiles.EXT), tiles_of(tmp_path / "map", "png")
    assert got and stats["web_tiles"] == len(got)
    assert sorted(got) == sorted(maps)          # the same positions, the same zooms
    zmax = int(stats["zooms"].split("-")[1])
    checked = wrong = off = 0
    for key, path in got.items():
        z, x, y = (int(v) for v in key.split("/"))
        tile = id_tiles.decode(path.read_bytes())
        if z == zmax:
            want, near = centres_lookup(ids, z, x, y)
            off += int((tile != want).sum())
            wrong += int((tile[..., None] != near).all(axis=-1).sum())
            checked += tile.size
        else:                                   # a parent is the 2 x 2 mode of its children
            quad = np.zeros((512, 512), np.uint32)
            for dy in (0, 1):
                for dx in (0, 1):
                    child = got.get(f"{z + 1}/{2 * x + dx}/{2 * y + dy}")
                    if child is not None:
                        quad[dy * 256:(dy + 1) * 256, dx * 256:(dx + 1) * 256] = id_tiles.decode(child.read_bytes())
            blocks = quad.reshape(256, 2, 256, 2).transpose(0, 2, 1, 3).reshape(256, 256, 4)
            counts = (blocks[..., :, None] == blocks[..., None, :]).sum(axis=2)
            assert (counts.max(axis=2) == (blocks == tile[..., None]).sum(axis=2)).all(), key
    assert checked > 100_000 and wrong == 0 and off < 0.005 * checked, (checked, wrong, off)
    assert {int(v) for p in got.values() for v in np.unique(id_tiles.decode(p.read_bytes()))} == \
        {0} | {r[4] for r in RECTS}


def test_a_tile_of_any_number_of_ids_decodes_to_itself():
    rng = np.random.default_rng(0)
    for n in (1, 2, 256, 257, 65536):                  # uint8 indices up to 256 ids, uint16 beyond
        tile = np.resize(rng.choice(2**32, n, replace=False).astype(np.uint32), (256, 256))
        rng.shuffle(tile.reshape(-1))
        assert np.array_equal(id_tiles.decode(id_tiles.encode(tile)), tile), n
        palette, index = np.unique(tile, return_inverse=True)     # the format, written out by its definition
        raw = (np.uint32(n).astype("<u4").tobytes() + palette.astype("<u4").tobytes()
               + index.astype("u1" if n <= 256 else "<u2").tobytes())
        assert id_tiles.encode(tile) == zlib.compress(raw, 9), n


def test_mode_keeps_the_majority_and_breaks_ties_at_the_bottom_right():
    quad = np.array([[1, 1, 5, 6], [1, 2, 7, 8], [3, 4, 9, 9], [3, 4, 0, 0]], np.uint32)
    assert id_tiles.mode2x2(quad).tolist() == [[1, 8], [4, 0]]


def test_an_id_update_rewrites_only_the_tiles_a_changed_object_reaches_and_equals_a_fresh_cut(tmp_path):
    _, before, _ = scene(tmp_path, name="a")
    changed = [*RECTS[:2], (250, 300, 420, 390, 3 << 22 | 6), RECTS[3]]       # one object renumbered
    _, after, _ = scene(tmp_path, changed, name="b")
    work, out = tmp_path / "work", tmp_path / "out"
    tms(before, "auto", out, tile_format="ids", work_dir=work)

    def ident(p):
        return os.stat(p).st_ino, os.stat(p).st_mtime_ns

    old = {k: ident(p) for k, p in tiles_of(out, id_tiles.EXT).items()}
    update = tms(after, "auto", out, tile_format="ids", work_dir=work)
    tms(after, "auto", tmp_path / "fresh", tile_format="ids")
    got, want = tiles_of(out, id_tiles.EXT), tiles_of(tmp_path / "fresh", id_tiles.EXT)
    assert sorted(got) == sorted(want)
    assert [k for k in want if got[k].read_bytes() != want[k].read_bytes()] == []
    redone = {k for k, p in got.items() if ident(p) != old.get(k)}
    assert not update["full"] and len(redone) == update["web_tiles_redone"]
    zmax = int(update["zooms"].split("-")[1])
    base = [k for k in got if k.startswith(f"{zmax}/")]
    assert 0 < len([k for k in redone if k in base]) < 0.5 * len(base)
    # every rewritten base tile lies within a block (4 tiles) of the renumbered rectangle
    x0, y1 = GRID.transform.c + 300 * 0.5, GRID.transform.f - 250 * 0.5
    box = transform_points(np.array([[x0, y1 - 85.0, 0], [x0 + 45.0, y1, 0]]), horizontal_wkt("EPSG:25832"),
                           WEB_MERCATOR)
    span = WORLD / 2 ** zmax
    for key in (k for k in redone if k in base):
        _, x, y = (int(v) for v in key.split("/"))
        tx0, ty1 = x * span - WORLD / 2, WORLD / 2 - y * span
        assert tx0 < box[1, 0] + 4 * span and tx0 + span > box[0, 0] - 4 * span, key
        assert ty1 - span < box[1, 1] + 4 * span and ty1 > box[0, 1] - 4 * span, key
