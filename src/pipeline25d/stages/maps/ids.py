"""A perspective's id map: which input object every map pixel shows, on the map's own grid.

The render tiles' object ids (:mod:`pipeline25d.stages.render_ids`, mosaicked as the colour tiles
are) go through the warp the map chose (its method, order and GCPs, recorded in
``maps/<id>.json``), resampled nearest neighbour: an id is never blended. They are made as the map
is: a sparse map's parts, each onto its window (:mod:`.parts`), or a dense map's fixed blocks kept
in ``work`` and redone only where the id or colour mosaic changed (:mod:`.patch`), so a district
update rewrites only the id blocks it reaches, and a patched id map equals a fresh one.

Nearest ids agree with the map's alpha although that is resampled bilinear: GDAL's warp kernel
leaves a map pixel empty when the source pixel under its centre (the one nearest neighbour takes)
is empty, and both warps run on the same windows, so their approximate transformer gives each
pixel the same source position. A render tile's ids are where its alpha is not 0
(:mod:`pipeline25d.stages.render_ids`), so a map pixel is opaque exactly where it has an id, up to
rounding (a faint edge's bilinear alpha written as 0). The id map is held to the map all the same:
an id where the map is transparent is cleared, an opaque pixel without an id takes the nearest id
in its block or part; both fixes are counted (0 on the tests' scenes and the demo), and every
opaque map pixel has an id and no transparent one has.
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import atomic_path, write_json
from pipeline25d.core.grid import Extent, Grid, Window
from pipeline25d.core.journal import read_state, write_state
from pipeline25d.core.raster import gdal, map_cells, stores_nothing
from pipeline25d.stages.gcps import read_observations
from pipeline25d.stages.maps.parts import overview_factors
from pipeline25d.stages.maps.patch import (
    BLOCK_PX,
    KEPT_OPTIONS,
    MARGIN_PX,
    block_window,
    blocks_reached,
    gcps_digest,
    kept_dataset,
    pixel_to_map,
    source_to_map,
    window_warp_options,
    write_block,
)

log = logging.getLogger(__name__)

STATE_VERSION = 1
KEPT = "ids.tif"
ID_COG = ["COMPRESS=DEFLATE", "PREDICTOR=2", "OVERVIEWS=FORCE_USE_EXISTING", "SPARSE_OK=TRUE"]   # as the map's


def id_map(ids_vrt: str | Path, mosaic_vrt: str | Path, gcps_csv: str | Path, map_json: str | Path,
           map_cog: str | Path, out: str | Path, stats_json: str | Path, work_dir: str | Path | None = None,
           threads: int = 1, cells_memo: dict | None = None) -> dict:
    """Write ``out`` (UInt32 COG, nodata 0) from the id mosaic ``ids_vrt`` with the warp the map
    ``map_cog`` was made with (``map_json``; its GCPs in ``gcps_csv``), and its figures to
    ``stats_json``: the fixes at edges, agreement with the map's alpha, bytes against the map's."""
    from pipeline25d.stages.maps.warp import encode_options, gcp_source, raster_grid, run_tool

    record = json.loads(Path(map_json).read_text())
    choice = {"method": record["method"], "order": record["order"]}
    ds = gdal().Open(str(map_cog))
    grid, crs = Grid.of_dataset(ds), ds.GetProjection()
    ds = None
    if raster_grid(ids_vrt) != raster_grid(mosaic_vrt):
        raise ValueError(f"{ids_vrt}: the id mosaic's grid is not the colour mosaic's ({mosaic_vrt})")
    factors = overview_factors(grid.width, grid.height)
    codec = ID_COG
    with atomic_path(out) as tmp:
        gcp_vrt = Path(tmp).with_suffix(".gcps.vrt")
        try:
            source = Path(ids_vrt)
            if choice["method"] != "none":
                source = gcp_source(ids_vrt, read_observations(gcps_csv), crs, gcp_vrt)
            maker = _Blocks(source, choice, crs, grid, map_cog, factors)
            if len(record["parts"]) > 1:
                stats = _sparse(maker, [_window_of(grid, Extent(*b)) for b in record["parts"]], tmp, codec, threads)
            else:
                kept_dir = Path(work_dir) if work_dir else Path(tmp).with_suffix(".blocks")
                try:
                    kept, stats = _patched(maker, ids_vrt, mosaic_vrt, kept_dir, cells_memo)
                    cog = [o for c in encode_options(codec, threads) for o in ("-co", c)]
                    run_tool(["gdal_translate", "-q", "-of", "COG", *cog, str(kept), str(tmp)])
                finally:
                    if not work_dir:
                        shutil.rmtree(kept_dir, ignore_errors=True)
        finally:
            gcp_vrt.unlink(missing_ok=True)
    stats = {**stats, **agreement(map_cog, out), "ids_bytes": Path(out).stat().st_size,
             "map_bytes": Path(map_cog).stat().st_size}
    write_json(stats_json, stats)
    disagree = stats["opaque_without_id"] or stats["transparent_with_id"] or stats["filled"] or stats["cleared"]
    (log.warning if disagree else log.info)(
        "id map %s: %d opaque px without an id, %d transparent px with one (%d filled, %d cleared at "
        "edges to hold it to the map); %d bytes, the map %d", Path(out).name, stats["opaque_without_id"],
        stats["transparent_with_id"], stats["filled"], stats["cleared"], stats["ids_bytes"], stats["map_bytes"])
    return stats


def _window_of(grid: Grid, e: Extent) -> Window:
    """The window of a part's bounds, which lie on the map's pixel edges (:func:`.parts.map_grid`)."""
    c0, r0 = grid.colrow(e.xmin, e.ymax)
    c1, r1 = grid.colrow(e.xmax, e.ymin)
    return Window(*(int(round(float(v))) for v in (c0, r0, c1, r1)))


class _Blocks:
    """Makes the id map's pixels over a window of the map grid: nearest ids through the map's warp
    (or copied, no warp), conformed to the map's alpha (module docstring)."""

    def __init__(self, source: Path, choice: dict, crs: str, grid: Grid, map_cog: str | Path, factors: list[int]):
        self.source, self.choice, self.crs, self.grid, self.factors = source, choice, crs, grid, factors
        self.map = gdal().Open(str(map_cog))

    def alpha(self, win: Window) -> np.ndarray:
        """The map's alpha (its 4th band, or a JPEG map's mask) over ``win``."""
        band = self.map.GetRasterBand(4) if self.map.RasterCount >= 4 else self.map.GetRasterBand(1).GetMaskBand()
        return band.ReadAsArray(win.col0, win.row0, win.width, win.height)

    def nothing_drawn(self, win: Window) -> bool:
        """Whether the map stores no pixel in ``win`` (its COG's unstored blocks: GDAL's data coverage
        EMPTY), where the ids, held to its alpha, are all 0."""
        return stores_nothing(self.map.GetRasterBand(1), win)

    def ids(self, win: Window) -> np.ndarray:
        """Nearest ids over ``win`` (uint32, 0 = none)."""
        g = gdal()
        if self.choice["method"] == "none":
            block = g.Translate("", str(self.source), format="MEM", srcWin=[win.col0, win.row0, win.width, win.height])
        else:
            opts = {k: v for k, v in window_warp_options(self.choice, self.crs, 1.0).items()
                    if k not in ("xRes", "yRes", "dstAlpha", "resampleAlg")}
            block = g.Warp("", str(self.source), format="MEM", outputBounds=self.grid.window_bounds(win),
                           width=win.width, height=win.height, resampleAlg="near", srcNodata=0, dstNodata=0, **opts)
        return block.GetRasterBand(1).ReadAsArray().astype(np.uint32)

    def make(self, win: Window) -> tuple[np.ndarray, int, int]:
        """(ids over ``win`` conformed to the map's alpha, filled, cleared); ``win`` is the window
        the map's own block or part was warped on."""
        ids, filled, cleared = conform(self.ids(win), self.alpha(win))
        return ids, int(filled.sum()), int(cleared.sum())

    def dataset(self, ids: np.ndarray, win: Window):
        """``ids`` as an in-memory raster on ``win`` of the map grid."""
        g = gdal()
        ds = g.GetDriverByName("MEM").Create("", win.width, win.height, 1, g.GDT_UInt32)
        ds.SetGeoTransform(self.grid.window(*win.slices).geotransform)
        ds.SetProjection(self.crs)
        ds.GetRasterBand(1).SetNoDataValue(0)
        ds.GetRasterBand(1).WriteArray(ids)
        return ds


def conform(ids: np.ndarray, alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ids, filled, cleared): ``ids`` made to agree with the map's ``alpha`` (module docstring):
    cleared where alpha is 0, and an opaque pixel without an id given the nearest pixel's id."""
    ids = ids.copy()
    cleared = (alpha == 0) & (ids != 0)
    ids[cleared] = 0
    filled = (alpha > 0) & (ids == 0)
    if filled.any() and ids.any():
        from scipy import ndimage as ndi

        _, (r, c) = ndi.distance_transform_edt(ids == 0, return_indices=True)
        ids[filled] = ids[r[filled], c[filled]]
    return ids, filled & (ids != 0), cleared


def _sparse(maker: _Blocks, windows: list[Window], out: Path, codec: list[str], threads: int) -> dict:
    """A sparse map's id map: each part's window (transparent at its edges) made whole, then assembled
    (``codec`` encoded by :func:`.warp.encode_options` with the job's ``threads``)."""
    from pipeline25d.stages.maps.parts import assemble_sparse_cog
    from pipeline25d.stages.maps.warp import encode_options

    g, files, filled, cleared = gdal(), [], 0, 0
    try:
        for k, win in enumerate(windows):
            ids, f, c = maker.make(win)
            filled, cleared = filled + f, cleared + c
            path = out.with_suffix(f".ids{k}.tif")
            files.append((path, win))
            g.GetDriverByName("GTiff").CreateCopy(str(path), maker.dataset(ids, win), options=["TILED=YES"])
            if maker.factors:
                ds = g.Open(str(path), 1)
                ds.BuildOverviews("NEAREST", maker.factors)
                ds = None
        assemble_sparse_cog(files, maker.grid, maker.crs, out, encode_options(codec, threads), ids=True)
    finally:
        for path, _ in files:
            path.unlink(missing_ok=True)
            Path(str(path) + ".ovr").unlink(missing_ok=True)
    return {"full": True, "parts": len(windows), "filled": filled, "cleared": cleared}


def _patched(maker: _Blocks, ids_vrt: str | Path, mosaic_vrt: str | Path, work: Path,
             cells_memo: dict | None = None) -> tuple[Path, dict]:
    """A dense map's id map kept in ``work`` and redone in the blocks that a changed square of the
    id or colour mosaic reaches (as :func:`.patch.patched_map` does for the map)."""
    grid, factors, choice = maker.grid, maker.factors, maker.choice
    warped = choice["method"] != "none"
    size = max(BLOCK_PX, factors[-1] if factors else 1)
    key = {"version": STATE_VERSION, "method": choice["method"], "order": choice.get("order"), "crs": maker.crs,
           "gcps": gcps_digest(maker.source) if warped else None, "grid": [*grid.geotransform, grid.width, grid.height],
           "block": size, "overviews": factors, "map_bands": maker.map.RasterCount}
    mosaic_grid, ids_cells = map_cells(ids_vrt)
    _, colour_cells = map_cells(mosaic_vrt, memo=cells_memo)
    cells = {k: ids_cells.get(k, "") + colour_cells.get(k, "") for k in ids_cells.keys() | colour_cells.keys()}
    key["mosaic"] = mosaic_grid
    state = read_state(work)
    full = state is None or state["key"] != key or not (work / KEPT).is_file()
    nx, ny = -(-grid.width // size), -(-grid.height // size)
    if full:
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        todo = {(bx, by) for bx in range(nx) for by in range(ny)}
        changed: list[str] = []
        fixes: dict[str, list[int]] = {}
    else:
        changed = sorted(c for c in cells.keys() | state["cells"].keys() if cells.get(c) != state["cells"].get(c))
        to_map = source_to_map(maker.source, choice) if warped else pixel_to_map(mosaic_grid)
        todo = {tuple(b) for b in state["dirty"]} | blocks_reached(changed, mosaic_grid, to_map, grid, size,
                                                                   MARGIN_PX if warped else 0)
        fixes = state["fixes"]
    todo = sorted(todo)
    write_state(work, {"key": key, "cells": {} if full else state["cells"], "fixes": fixes, "dirty": todo})
    with kept_dataset(work / KEPT, full, grid, maker.crs, factors, 1, "UInt32", KEPT_OPTIONS, nodata=0) as kept:
        for bx, by in todo:
            win = block_window(bx, by, grid.width, grid.height, size)
            if full and maker.nothing_drawn(win):     # its ids all cleared: a new kept file holds those zeros
                fixes[f"{bx}_{by}"] = [0, 0]
                continue
            ids, filled, cleared = maker.make(win)
            fixes[f"{bx}_{by}"] = [filled, cleared]
            if not full or ids.any():
                write_block(kept, maker.dataset(ids, win), win, factors, "NEAREST")
    write_state(work, {"key": key, "cells": cells, "fixes": fixes, "dirty": []})
    log.info("id map: %s; %d mosaic squares changed, %d of %d blocks %s", "full" if full else "patch",
             len(changed), len(todo), nx * ny, "warped" if warped else "copied")
    return work / KEPT, {"full": full, "parts": 1, "mosaic_cells_changed": len(changed), "blocks_redone": len(todo),
                         "blocks": nx * ny, "filled": sum(f for f, _ in fixes.values()),
                         "cleared": sum(c for _, c in fixes.values())}


def agreement(map_cog: str | Path, ids_cog: str | Path, rows: int = 1024) -> dict:
    """Opaque map pixels (alpha > 0), those without an id, and transparent ones with an id,
    counted over the whole map in strips of ``rows``."""
    g = gdal()
    m, i = g.Open(str(map_cog)), g.Open(str(ids_cog))
    alpha = m.GetRasterBand(4) if m.RasterCount >= 4 else m.GetRasterBand(1).GetMaskBand()
    band = i.GetRasterBand(1)
    opaque = without = stray = 0
    for r in range(0, m.RasterYSize, rows):
        n = min(rows, m.RasterYSize - r)
        a = alpha.ReadAsArray(0, r, m.RasterXSize, n) > 0
        has = band.ReadAsArray(0, r, m.RasterXSize, n) != 0
        opaque, without, stray = opaque + int(a.sum()), without + int((a & ~has).sum()), stray + int((~a & has).sum())
    return {"opaque_px": opaque, "opaque_without_id": without, "transparent_with_id": stray}
