"""A warped map kept between runs and patched where its mosaic changed.

The GCP warp of a map is done in fixed *blocks* of :data:`BLOCK_PX` x :data:`BLOCK_PX` pixels of
the map grid, each warped by GDAL on its own window into a kept, tiled GeoTIFF; the COG is then
copied from that file. A later run hashes the mosaic in squares of
:data:`pipeline25d.web_tiles.CELL_PX` pixels and warps again only the blocks that a changed
square reaches through the warp (its outline mapped by the same GCP transformer, grown by
:data:`MARGIN_PX` for the bilinear kernel and gdalwarp's approximation). As every block is always
warped on its own window, a patched map equals, byte for byte, one warped from scratch. A
changed warp (method, order, GCPs), map grid or CRS warps every block again. The state file
journals the blocks being redone before the kept file is touched, so a killed run is finished
by the next one.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
from pathlib import Path

import numpy as np

from .journal import read_state, write_state
from .map_parts import Window, box_outline, window_bounds
from .raster import gdal

log = logging.getLogger(__name__)

BLOCK_PX = 2048        # a multiple of the COG's largest overview factor (2 ** 11 > any map's overview count)
MARGIN_PX = 2          # a changed mosaic square reaches this far (map px) beyond its warped outline
EDGE_SAMPLES = 9       # points per square edge sent through the warp (a polynomial bends the edge)
STATE_VERSION = 1
KEPT = "map.tif"


def warp_options(choice: dict, crs: str, gsd: float) -> dict:
    """gdal.Warp keywords of the chosen GCP warp onto the map grid (as gdalwarp -tap at ``gsd``)."""
    opts = {"dstSRS": crs, "xRes": gsd, "yRes": gsd, "targetAlignedPixels": True, "dstAlpha": True,
            "resampleAlg": "bilinear", "multithread": True, "warpOptions": ["NUM_THREADS=ALL_CPUS"]}
    if choice["method"] == "tps":
        opts["tps"] = True
    else:
        opts["polynomialOrder"] = choice["order"]
    return opts


def source_to_map(source: str | Path, choice: dict):
    """(x, y) in mosaic pixels -> (x, y) on the map, through GDAL's GCP transformer of ``source``."""
    from .warp import transformer_options

    g = gdal()
    transformer = g.Transformer(g.Open(str(source)), None, transformer_options(choice["method"], choice["order"]))

    def to_map(col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xy, _ = transformer.TransformPoints(0, np.column_stack([col, row, np.zeros(len(col))]).tolist())
        xy = np.asarray(xy, dtype=np.float64)
        return xy[:, 0], xy[:, 1]

    return to_map


def patched_map(source: str | Path, choice: dict, crs: str, gsd: float, work: Path) -> tuple[Path, dict]:
    """Bring the warped map kept in ``work`` up to ``source`` (a VRT of the mosaic with its GCPs);
    return the kept GeoTIFF and the run's figures (full or not, squares changed, blocks warped)."""
    from .web_tiles import map_cells

    g = gdal()
    grid_vrt = g.Warp("", str(source), format="VRT", **warp_options(choice, crs, gsd))
    gt, width, height = grid_vrt.GetGeoTransform(), grid_vrt.RasterXSize, grid_vrt.RasterYSize
    bands = grid_vrt.RasterCount
    grid_vrt = None
    src = g.Open(str(source))
    gcps = [(p.GCPPixel, p.GCPLine, p.GCPX, p.GCPY, p.GCPZ) for p in src.GetGCPs()]
    src = None
    key = {"version": STATE_VERSION, "method": choice["method"], "order": choice["order"], "crs": crs,
           "gcps": hashlib.sha256(json.dumps(gcps).encode()).hexdigest()[:16], "grid": [*gt, width, height],
           "block": BLOCK_PX}
    mosaic_grid, cells = map_cells(source)
    key["mosaic"] = mosaic_grid
    state = read_state(work)
    full = state is None or state["key"] != key or not (work / KEPT).is_file()
    if full:
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        _create_kept(work / KEPT, gt, width, height, bands, crs)
        todo = {(bx, by) for bx in range(-(-width // BLOCK_PX)) for by in range(-(-height // BLOCK_PX))}
        changed: list[str] = []
    else:
        old = state["cells"]
        changed = sorted(c for c in cells.keys() | old.keys() if cells.get(c) != old.get(c))
        todo = {tuple(b) for b in state["dirty"]} | blocks_reached(changed, mosaic_grid, source_to_map(source, choice),
                                                                   gt, width, height)
    todo = sorted(todo)
    write_state(work, {"key": key, "cells": {} if full else state["cells"], "dirty": todo})    # journal first
    kept = g.Open(str(work / KEPT), 1)
    for bx, by in todo:
        win = block_window(bx, by, width, height)
        opts = {k: v for k, v in warp_options(choice, crs, gsd).items() if k not in ("xRes", "yRes", "targetAlignedPixels")}
        block = g.Warp("", str(source), format="MEM", outputBounds=window_bounds(gt, win), width=win.width,
                       height=win.height, **opts)
        kept.WriteRaster(win.col0, win.row0, win.width, win.height, block.ReadRaster())
    kept.FlushCache()
    kept = None
    write_state(work, {"key": key, "cells": cells, "dirty": []})
    stats = {"full": full, "mosaic_cells_changed": len(changed), "blocks_warped": len(todo),
             "blocks": -(-width // BLOCK_PX) * -(-height // BLOCK_PX)}
    log.info("warp: %s; %d mosaic squares changed, %d of %d map blocks warped", "full" if full else "patch",
             len(changed), len(todo), stats["blocks"])
    return work / KEPT, stats


def block_window(bx: int, by: int, width: int, height: int) -> Window:
    """The pixel window of block (bx, by) of a map ``width`` x ``height``."""
    return Window(bx * BLOCK_PX, by * BLOCK_PX, min((bx + 1) * BLOCK_PX, width), min((by + 1) * BLOCK_PX, height))


def blocks_reached(cell_ids: list[str], mosaic_grid: list, to_map, gt: tuple[float, ...], width: int,
                   height: int) -> set[tuple[int, int]]:
    """The map blocks that mosaic squares ``cell_ids`` (of :func:`pipeline25d.web_tiles.map_cells`)
    reach through the warp ``to_map`` (mosaic pixels -> map x, y)."""
    if not cell_ids:
        return set()
    cell, mw, mh = mosaic_grid[8], mosaic_grid[6], mosaic_grid[7]
    ids = np.array([[int(v) for v in c.split("_")] for c in cell_ids])
    c0, r0 = ids[:, 0] * cell, ids[:, 1] * cell
    c1, r1 = np.minimum(c0 + cell, mw), np.minimum(r0 + cell, mh)
    outlines = [box_outline(*b, n=EDGE_SAMPLES) for b in zip(c0, r0, c1, r1)]
    x, y = to_map(np.concatenate([o[0] for o in outlines]), np.concatenate([o[1] for o in outlines]))
    col = ((x - gt[0]) / gt[1]).reshape(len(cell_ids), -1)
    row = ((y - gt[3]) / gt[5]).reshape(len(cell_ids), -1)
    out = set()
    for a0, a1, b0, b1 in zip(col.min(axis=1), col.max(axis=1), row.min(axis=1), row.max(axis=1)):
        a0, b0 = max(int(np.floor(a0)) - MARGIN_PX, 0), max(int(np.floor(b0)) - MARGIN_PX, 0)
        a1, b1 = min(int(np.ceil(a1)) + MARGIN_PX, width - 1), min(int(np.ceil(b1)) + MARGIN_PX, height - 1)
        if a1 >= a0 and b1 >= b0:
            out |= {(bx, by) for bx in range(a0 // BLOCK_PX, a1 // BLOCK_PX + 1)
                    for by in range(b0 // BLOCK_PX, b1 // BLOCK_PX + 1)}
    return out


def _create_kept(path: Path, gt: tuple[float, ...], width: int, height: int, bands: int, crs: str) -> None:
    g = gdal()
    ds = g.GetDriverByName("GTiff").Create(str(path), width, height, bands, g.GDT_Byte,
                                           ["TILED=YES", "BLOCKXSIZE=512", "BLOCKYSIZE=512", "COMPRESS=ZSTD",
                                            "ZSTD_LEVEL=1", "SPARSE_OK=TRUE", "BIGTIFF=IF_SAFER",
                                            *(["PHOTOMETRIC=RGB"] if bands >= 4 else []), "ALPHA=YES"])
    ds.SetGeoTransform(gt)
    ds.SetProjection(crs)
    ds = None

