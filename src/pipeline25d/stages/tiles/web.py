"""The XYZ web-tile pyramid of a map, cut block by block and kept up to date.

The map is reprojected to EPSG:3857 in *blocks*: squares of :data:`BLOCK_TILES` x
:data:`BLOCK_TILES` web tiles of the highest zoom, each warped by gdalwarp in C onto the
whole map's web-mercator grid (on the tile grid's pixels: :func:`tile_grid`), with the
nearest-neighbour resampling of gdal2tiles' own warped VRT (transform exact to 0.01 px). Where that
grid is finer than the tiles' (a map's: 2 or 4 of its pixels a side to a tile pixel), a block is kept
as the average that gdal2tiles' base tile takes of it (:mod:`.blocks`), on the
tiles' own pixels: a quarter of the pixels to compress, keep and read again, the same tiles.
gdal2tiles then cuts a VRT of the blocks with its
own tile functions: base tiles by ``create_base_tile`` (its read made fast, same bytes: see
:mod:`pipeline25d.stages.tiles.base`), overview tiles from their children by
``create_overview_tile``. It reads plain windows instead of re-warping for every tile,
blocks over nothing the map stores (a sparse COG's unstored blocks) are not warped at all, and
only tiles that hold data are written, so a sparse map costs its districts, not its bounding box.

A pyramid kept in a work folder is *updated*: the map is hashed in squares of
:data:`CELL_PX` pixels, and only the web-mercator blocks within reach of a changed square are
warped again; the base tiles whose read window meets that reach and every tile above them are
deleted and cut again. As every block is always warped on its own window, an update gives
the same tiles, byte for byte, as a cut from scratch. A state file journals the reach being
redone, so a killed update is finished by the next one.

An object-id raster (``maps/<id>.ids.tif``) is cut the same way with ``tile_format="ids"``:
the same blocks and tile positions, each tile the ids of its pixels
(:mod:`pipeline25d.stages.tiles.ids`).
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from functools import partial
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import device_full, replace_dir
from pipeline25d.core.errors import OutputError
from pipeline25d.core.grid import Extent, Grid, Window, windows_meeting
from pipeline25d.core.journal import read_state, write_state
from pipeline25d.core.raster import cells_grid_of, gdal, map_cells, noted_cells
from pipeline25d.stages.maps.mosaic_sources import plain_sources
from pipeline25d.stages.maps.parts import box_outline
from pipeline25d.stages.tiles import ids as id_tiles
from pipeline25d.stages.tiles.base import close_source, create_base_tile, gdal2tiles
from pipeline25d.stages.tiles.blocks import (
    GDAL2TILES_TILE,
    WEB_MERCATOR,
    over_nothing,
    stored_factor,
    stored_grid,
    tile_metres,
    warp_block,
)
from pipeline25d.stages.tiles.workers import Workers

log = logging.getLogger(__name__)

BLOCK_TILES = 4        # a web-mercator block is 4 x 4 tiles of the highest zoom (1024 x 1024 px)
MARGIN_PX = 2          # a changed map cell reaches this far (web-mercator px) beyond its reprojected outline
EDGE_SAMPLES = 5       # points per cell edge reprojected (a cell is small: the reprojection is near affine)
STATE_VERSION = 2      # 2: blocks kept averaged to the tiles' pixels (blocks.STORED_FACTORS)


def tms(cog: str | Path, zoom: str, out_dir: str | Path, processes: int = 1, tile_format: str = "png",
        quality: int = 85, work_dir: str | Path | None = None, most: int | None = None,
        webp_method: int | None = None, cells_note: str | Path | None = None) -> dict:
    """The gdal2tiles XYZ pyramid (web mercator) of a map at ``out_dir``, published atomically.

    ``tile_format`` png or webp (lossy at ``quality``, with alpha; ``webp_method``: libwebp's
    effort, 0-6, None its default 4, which gdal2tiles uses), or ids (``cog`` is then an
    object-id raster: :mod:`pipeline25d.stages.tiles.ids`). ``work_dir`` keeps the
    pyramid, its blocks and its state between runs, so that the next call redoes only what
    changed in the map; without it the pyramid is cut from scratch. Returns the cut's
    figures: web tiles in all, web tiles redone, blocks warped, and whether it was a full cut.
    ``processes``: the worker processes each stage of the cut starts with; ``most``: those it may
    grow to while cores are idle (:class:`Workers`; default ``processes``). ``cells_note``: the
    map's digests as its warp kept them (:func:`~pipeline25d.core.raster.noted_cells`), read
    instead of the map where they are of this version of it.
    """
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    for stale in out_dir.parent.glob(f".{out_dir.name}.*"):        # what a killed cut left behind
        if stale.is_dir():
            shutil.rmtree(stale)
        else:
            stale.unlink()
    if work_dir is not None:
        with _space_checked(Path(work_dir)):
            stats = update_pyramid(cog, zoom, Path(work_dir), processes, tile_format, quality, most, webp_method,
                                   cells_note)
        publish(Path(work_dir) / "tiles", out_dir)
        return stats
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    try:
        with _space_checked(tmp):
            stats = update_pyramid(cog, zoom, tmp / "work", processes, tile_format, quality, most, webp_method,
                                   cells_note)
        publish(tmp / "work" / "tiles", out_dir)
        return stats
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


@contextmanager
def _space_checked(work: Path) -> Iterator[None]:
    """An error of the cut while the device of ``work`` is full becomes an OutputError naming
    it (gdal2tiles writes its tiles in place and GDAL does not say why a write failed); the
    state's journal has the next cut redo what this one left."""
    try:
        yield
    except (OSError, RuntimeError) as exc:
        if isinstance(exc, OutputError) or not device_full(work, exc):
            raise
        raise OutputError(work, f"No space left on device while cutting web tiles ({exc})") from exc


def publish(tiles: Path, out_dir: Path) -> None:
    """Hard-link the kept pyramid's files into a new folder and move it onto ``out_dir``: no tile
    is copied, and a later update, which replaces files rather than rewriting them, leaves the
    published ones as they are."""
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    try:
        for src in sorted(tiles.rglob("*")) if tiles.is_dir() else []:
            dst = tmp / src.relative_to(tiles)
            if src.is_dir():
                dst.mkdir(exist_ok=True)
            else:
                os.link(src, dst)
        replace_dir(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def update_pyramid(cog: str | Path, zoom: str, work: Path, processes: int = 1, tile_format: str = "png",
                   quality: int = 85, most: int | None = None, webp_method: int | None = None,
                   cells_note: str | Path | None = None) -> dict:
    """Bring the pyramid kept in ``work`` (``tiles/``, ``blocks/``, ``state.json``) up to the map ``cog``
    (its digests from ``cells_note`` where it has them: :func:`tms`)."""
    gdal2tiles()                       # before the workers fork: they inherit its tile options
    g = gdal()
    ds = g.Open(str(cog))
    wkt = ds.GetProjection()
    ds = None
    grid, zooms = tile_grid(cog, zoom, halved=tile_format != "ids")
    width, height = grid.width, grid.height
    max_zoom = int(zooms.split("-")[-1])
    factor = stored_factor(grid, max_zoom)
    key = {"version": STATE_VERSION, "grid": [*grid.geotransform, width, height], "zooms": zooms, "format": tile_format,
           "quality": int(quality) if tile_format == "webp" else None, "block_tiles": BLOCK_TILES,
           **({"webp_method": webp_method} if tile_format == "webp" and webp_method is not None else {})}
    noted = noted_cells(cells_note, cog)
    map_grid, cells = noted or map_cells(cog)
    log.info("map digests: %s", "as its warp job made them" if noted else "read from the map")
    key["map"] = map_grid
    state = read_state(work)
    full = state is None or state["key"] != key
    if full:
        shutil.rmtree(work, ignore_errors=True)
        state = {"key": key, "cells": {}, "dirty": []}
    (work / "blocks").mkdir(parents=True, exist_ok=True)
    old = state["cells"]
    changed = [cell_bounds(c, map_grid) for c in sorted(cells.keys() | old.keys()) if cells.get(c) != old.get(c)]
    # journal first: a killed update is redone by the next one, whatever the map is by then
    reach = [Window(0, 0, width, height)] if full else \
        [Window(*w) for w in state["dirty"]] + mercator_reach(changed, wkt, grid)
    write_state(work, {**state, "dirty": reach})
    todo = sorted({b for w in reach for b in blocks_meeting(w, grid, max_zoom)})
    jobs = [(b, w) for b, w in ((b, block_window(b, grid, max_zoom)) for b in todo) if w is not None]
    nothing = over_nothing(str(cog), grid, jobs)      # not warped: the tiles read zeros there and are not written
    for b in nothing:
        (work / "blocks" / f"{b[0]}_{b[1]}.tif").unlink(missing_ok=True)
    with Workers(processes, most) as workers:
        workers.map(partial(warp_block, str(cog), str(work / "blocks"), grid, tile_format == "ids", factor),
                    [j for j in jobs if j[0] not in nothing])
        blocks = sorted((work / "blocks").glob("*.tif"))
        if blocks:
            held = [block_window(tuple(int(v) for v in b.stem.split("_")), grid, max_zoom) for b in blocks]
            redone = cut(blocks, work / "tiles", stored_grid(grid, factor), zooms,
                         [w.scaled_down(factor) for w in reach], workers, tile_format, quality, webp_method,
                         [w.scaled_down(factor) for w in held if w is not None])
        else:                           # the map stores nothing: no tile holds anything
            shutil.rmtree(work / "tiles", ignore_errors=True)
            (work / "tiles").mkdir()
            redone = 0
    write_state(work, {"key": key, "cells": cells, "dirty": []})
    warped = len(jobs) - len(nothing)
    stats = {"full": full, "map_cells_changed": len(changed), "blocks_warped": warped,
             "blocks_over_nothing": len(nothing), "web_tiles_redone": redone,
             "web_tiles": sum(1 for p in (work / "tiles").rglob("*") if p.is_file()), "zooms": zooms}
    log.info("web tiles: %s; %d of %d map cells changed, %d web-mercator blocks warped (%d more over nothing the "
             "map stores), %d of %d web tiles redone (workers: %d at each stage's start, %d more taken as cores fell "
             "idle)", "full cut" if full else "update", len(changed), len(cells), warped, len(nothing), redone,
             stats["web_tiles"], workers.processes, workers.grown)
    return stats


def cell_bounds(cell_id: str, cells_grid: list) -> Extent:
    """The world rectangle, in the map's CRS, of a map cell of :func:`map_cells`."""
    grid, cell = cells_grid_of(cells_grid), cells_grid[8]
    col, row = (int(v) for v in cell_id.split("_"))
    c0, r0 = col * cell, row * cell
    return grid.window_bounds(Window(c0, r0, min(c0 + cell, grid.width), min(r0 + cell, grid.height)))


def _block_metres(max_zoom: int) -> tuple[float, float]:
    origin, tile = tile_metres(max_zoom)
    return origin, BLOCK_TILES * tile


def mercator_reach(bounds: list[Extent], crs_wkt: str, grid: Grid) -> list[Window]:
    """The pixel windows of the web-mercator ``grid`` that map rectangles
    ``bounds`` reach: each one's reprojected outline, grown by :data:`MARGIN_PX` and clipped
    (nearest-neighbour: a pixel beyond it never reads the rectangle)."""
    from pipeline25d.core.crs import transform_points

    if not bounds:
        return []
    outlines = [box_outline(*b, n=EDGE_SAMPLES) for b in bounds]
    xy = np.column_stack([np.concatenate([o[0] for o in outlines]), np.concatenate([o[1] for o in outlines])])
    m = transform_points(np.column_stack([xy, np.zeros(len(xy))]), crs_wkt, WEB_MERCATOR)
    m = m.reshape(len(bounds), -1, 3)
    c0, r0 = grid.colrow(m[..., 0].min(axis=1), m[..., 1].max(axis=1))
    c1, r1 = grid.colrow(m[..., 0].max(axis=1), m[..., 1].min(axis=1))
    c0, r0 = np.floor(c0).astype(int) - MARGIN_PX, np.floor(r0).astype(int) - MARGIN_PX
    c1, r1 = np.ceil(c1).astype(int) + MARGIN_PX, np.ceil(r1).astype(int) + MARGIN_PX
    width, height = grid.width, grid.height
    windows = zip(np.clip(c0, 0, width), np.clip(r0, 0, height), np.clip(c1, 0, width), np.clip(r1, 0, height))
    return [Window(*(int(v) for v in w)) for w in windows if w[2] > w[0] and w[3] > w[1]]


def blocks_meeting(window: Window, grid: Grid, max_zoom: int) -> set[tuple[int, int]]:
    """The web-mercator blocks (bx, by; y up) that a pixel window of the grid meets."""
    origin, size = _block_metres(max_zoom)
    x0, y0, x1, y1 = grid.window_bounds(window)
    bx0, bx1 = int(np.floor((x0 + origin) / size)), int(np.floor((x1 + origin) / size))
    by0, by1 = int(np.floor((y0 + origin) / size)), int(np.floor((y1 + origin) / size))
    return {(bx, by) for bx in range(bx0, bx1 + 1) for by in range(by0, by1 + 1)}


def block_window(block: tuple[int, int], grid: Grid, max_zoom: int) -> Window | None:
    """A block's pixel window on the map's web-mercator grid; blocks share their edges, rounded
    to the grid's pixels. None where it misses the grid."""
    origin, size = _block_metres(max_zoom)
    x0, y0 = block[0] * size - origin, block[1] * size - origin
    c0, r0 = grid.colrow(x0, y0 + size)
    c1, r1 = grid.colrow(x0 + size, y0)
    c0, r0, c1, r1 = max(round(c0), 0), max(round(r0), 0), min(round(c1), grid.width), min(round(r1), grid.height)
    return Window(c0, r0, c1, r1) if c1 > c0 and r1 > r0 else None


def cut(blocks: list[Path], tiles: Path, grid: Grid, zooms: str, windows: list[Window], workers: Workers,
        tile_format: str, quality: int, webp_method: int | None = None,
        held_windows: list[Window] | None = None) -> int:
    """Cut again, with gdal2tiles' own tile functions, every web tile that ``windows`` (pixel
    windows of the web-mercator grid whose blocks were warped again) reach: the base tiles
    whose read window meets one, and all tiles above them. Their old files are deleted first,
    so a tile that now holds nothing is gone. A base tile whose read window meets none of the
    ``blocks`` (their windows on ``grid``: ``held_windows``, default the whole grid) is not made:
    it would read zeros, and gdal2tiles writes no empty tile (a map of Zurich's 210 LoD2 buildings
    over 9 x 10 km at 0.5 m: at zooms 11-17, 1,008 base tiles made where 2,350 were; at 14-18,
    2,158 where 9,108 were). Returns how many tiles were written."""
    g2t = gdal2tiles()
    if not windows:
        return 0
    tiles.mkdir(parents=True, exist_ok=True)
    vrt = tiles.parent / "blocks.vrt"
    gdal().BuildVRT(str(vrt), [str(b) for b in blocks], outputBounds=grid.bounds, xRes=grid.transform.a,
                    yRes=-grid.transform.e)          # not kept: dropped, it is written
    # blocks never overlap, and gdalwarp leaves a block's colour 0 (an id block's 0) where it is
    # transparent: read as plain copies, not composited through their masks (the same pixels)
    plain_sources(vrt)
    ids = tile_format == "ids"
    layout = vrt
    if ids:         # gdal2tiles lays out only 8-bit rasters: its tiles' windows from a Byte view of the ids
        layout = tiles.parent / "blocks.byte.vrt"
        gdal().Translate(str(layout), str(vrt), format="VRT", outputType=gdal().GDT_Byte)
    _, _, options = g2t.process_args([*_gdal2tiles_args(zooms, workers.processes, tile_format, quality, True),
                                      str(layout), str(tiles)])
    options.webp_method = webp_method             # read by the tile encoder (tiles.base.gdal2tiles)
    conf, details = g2t.worker_tile_details(str(layout), str(tiles), options)
    try:
        reads = np.array([[d.rx, d.ry, d.rx + d.rxsize, d.ry + d.rysize] for d in details]).reshape(-1, 4)
        held_windows = [Window(0, 0, grid.width, grid.height)] if held_windows is None else held_windows
        meets, held = windows_meeting(reads, windows, grid), windows_meeting(reads, held_windows, grid)
        base = [d for d, m, h in zip(details, meets, held) if m and h]
        reach = {conf.tmaxz: {(d.tx, d.ty) for d, m in zip(details, meets) if m}}     # xyz positions, as on disk
        for z in range(conf.tmaxz - 1, conf.tminz - 1, -1):
            reach[z] = {(x >> 1, y >> 1) for x, y in reach[z + 1]}
        ext = id_tiles.EXT if ids else conf.tile_extension
        for z, cells in reach.items():
            for x, y in cells:
                (tiles / str(z) / str(x) / f"{y}.{ext}").unlink(missing_ok=True)
        if ids:
            _cut_ids(str(vrt), tiles, base, reach, conf, workers)
            return sum(id_tiles.tile_path(tiles, z, x, y).is_file() for z, cells in reach.items() for x, y in cells)
        workers.map(partial(create_base_tile, conf), base)
        for base_z in range(conf.tmaxz, conf.tminz, -1):
            groups = [grp for grp in g2t.group_overview_base_tiles(base_z, str(tiles), conf)
                      if (grp[0][0] >> 1, g2t.GDAL2Tiles.getYTile(grp[0][1] >> 1, base_z - 1, options))
                      in reach[base_z - 1]]
            workers.map(partial(g2t.create_overview_tile, base_z, output_folder=str(tiles), tile_job_info=conf,
                         options=options), groups)
    finally:
        close_source()
        shutil.rmtree(os.path.dirname(conf.src_file), ignore_errors=True)
        vrt.unlink(missing_ok=True)
        layout.unlink(missing_ok=True)
    return sum((tiles / str(z) / str(x) / f"{y}.{conf.tile_extension}").is_file()
               for z, cells in reach.items() for x, y in cells)


def _cut_ids(vrt: str, tiles: Path, base: list, reach: dict[int, set], conf, workers: Workers) -> None:
    """The id tiles of a cut: base tiles of ``base`` (gdal2tiles' tile details) from the VRT, then
    every tile of ``reach`` above them, zoom by zoom, from its children."""
    for d in base:                      # gdal2tiles makes the folders of its own tiles
        (tiles / str(d.tz) / str(d.tx)).mkdir(parents=True, exist_ok=True)
    workers.map(partial(id_tiles.base_tile, vrt, str(tiles)), base)
    for z in range(conf.tmaxz - 1, conf.tminz - 1, -1):
        workers.map(partial(id_tiles.overview_tile, str(tiles)), sorted((z, x, y) for x, y in reach[z]))


def _gdal2tiles_args(zoom: str, processes: int, tile_format: str, quality: int, exclude_empty: bool) -> list[str]:
    args = ["-q", "--xyz", "-w", "none", "-r", "near" if tile_format == "ids" else "average",
            f"--processes={processes}", *(["--exclude"] if exclude_empty else [])]
    if tile_format == "webp":
        args += ["--tiledriver=WEBP", f"--webp-quality={int(quality)}"]
    if zoom != "auto":
        args += ["-z", zoom]
    return args


def mercator_grid(cog: str | Path) -> Grid:
    """The grid of the whole map reprojected to web mercator, as gdalwarp makes it."""
    g = gdal()
    vrt = g.Warp("", str(cog), format="VRT", dstSRS=WEB_MERCATOR, resampleAlg="near", errorThreshold=0.01,
                 dstAlpha=True)
    return Grid.of_dataset(vrt)


def tile_grid(cog: str | Path, zoom: str, halved: bool = True) -> tuple[Grid, str]:
    """The web-mercator grid the map is warped onto, and its zooms ("min-max"; ``zoom`` "auto":
    :func:`zoom_range` of gdalwarp's own grid). The grid lies on the web-tile grid: its pixel is the
    highest zoom's tile pixel, ``halved`` until no coarser than gdalwarp's (not for an id raster: a
    tile takes its ids by nearest neighbour, one per pixel), its edges those of the highest zoom's
    tiles. So every base tile reads a whole window of it, no tile clipped at its edge: gdal2tiles
    takes a tile's window from its offset rounded toward zero, so on gdalwarp's own grid each base tile
    moved by up to a source pixel (a road by up to a map pixel on the web tiles), and a tile clipped at
    the grid's left or top edge by one more."""
    native = mercator_grid(cog)
    zooms = zoom_range(native) if zoom == "auto" else zoom
    origin, tile = tile_metres(int(zooms.split("-")[-1]))            # the highest zoom's tile, metres
    size = tile / GDAL2TILES_TILE
    while halved and size > native.transform.a * (1 + 1e-9):
        size /= 2
    x0, y0, x1, y1 = native.bounds
    c0, r0 = np.floor((x0 + origin) / tile + 1e-9), np.floor((origin - y1) / tile + 1e-9)
    c1, r1 = np.ceil((x1 + origin) / tile - 1e-9), np.ceil((origin - y0) / tile - 1e-9)
    n = round(tile / size)                                              # pixels a tile
    return Grid.north_up(c0 * tile - origin, origin - r0 * tile, size, int(c1 - c0) * n, int(r1 - r0) * n), zooms


def zoom_range(grid: Grid) -> str:
    """gdal2tiles' automatic zoom levels for a web-mercator raster: "min-max"."""
    from osgeo_utils.gdal2tiles import GlobalMercator

    merc = GlobalMercator(GDAL2TILES_TILE)
    zmin = merc.ZoomForPixelSize(grid.transform.a * max(grid.width, grid.height) / GDAL2TILES_TILE)
    zmax = max(zmin, merc.ZoomForPixelSize(grid.transform.a))
    return f"{zmin}-{zmax}"
