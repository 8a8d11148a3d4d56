"""Plan one perspective: the non-empty tiles, each with its chunks, LODs and GCPs.

Tiles lie on a global grid: tile (row, col) covers map x in [col·S, (col+1)·S) and y in
[row·S, (row+1)·S) with S = tile_size·gsd, so rows count northward. A tile's id and
extent therefore do not depend on the rest of the scene: adding or changing a district
leaves the other tiles' jobs untouched. A tile that no chunk's projected bounding box
touches is empty and gets no job. Each tile carries its own depth range (from its
chunks), the GCP candidates whose projected centre it holds and its content box (where its
chunks' projected boxes meet it: nothing outside can be drawn).
"""

from __future__ import annotations

import hashlib
import json
import math
from functools import lru_cache
from pathlib import Path

import numpy as np

from .camera import Extent, pixel_size, project, project_above_ground, projected_box
from .gcps import CANDIDATE_FIELDS
from .lod import choose_level
from .perspectives import Perspective

DEPTH_MARGIN_M = 1.0   # keeps surfaces at a tile's depth range ends off its near/far planes


def tile_span(gsd: float, tile_size: int) -> float:
    return gsd * tile_size


def plan_pixel(plan: dict) -> float:
    """Metres per render pixel: the gsd, or the paper camera's image-plane pixel."""
    return plan.get("pixel_size", plan["gsd"])


def camera_of(projection: str | None) -> str:
    """The camera a projection renders with: the paper's image plane, else the map-aligned one."""
    return "paper" if projection == "paper" else "map"


def plan_camera(plan: dict) -> str:
    return camera_of(plan.get("projection"))


def tile_extent(plan: dict, row: int, col: int, margin_px: int = 0) -> Extent:
    """Map (or paper image) extent of tile (row, col), optionally grown by ``margin_px`` on every side."""
    px = plan_pixel(plan)
    span = tile_span(px, plan["tile_size"])
    m = margin_px * px
    return Extent(col * span - m, row * span - m, (col + 1) * span + m, (row + 1) * span + m)


def tile_content(plan: dict, tile: dict) -> tuple[Extent, tuple[int, int]]:
    """The extent a tile renders and its size in pixels: its content box (whole pixels), or the
    whole tile for plans without one. Nothing can be drawn outside it."""
    px = plan_pixel(plan)
    e = Extent(*tile["content"]) if "content" in tile else tile_extent(plan, tile["row"], tile["col"])
    return e, (max(round((e.xmax - e.xmin) / px), 1), max(round((e.ymax - e.ymin) / px), 1))


def extent_geotransform(plan: dict, e: Extent) -> tuple[float, ...]:
    """GDAL geotransform of a render extent (top-left corner, north up)."""
    return (e.xmin, plan_pixel(plan), 0.0, e.ymax, 0.0, -plan_pixel(plan))


def _index_range(lo: float, hi: float, span: float) -> range:
    return range(math.floor(lo / span), math.floor(hi / span) + 1)


def plan_perspective(p: Perspective, chunks: list[dict], candidates: list[dict], z0: float, gsd: float,
                     tile_size: int, max_error_px: float, crs: str, render: dict,
                     terrain: dict | None = None) -> dict:
    """The plan of perspective ``p`` as a JSON-able dict.

    ``chunks``: [{"id", "district", "bounds" (2,3), "errors": [m per level]}, plus "ground"
    (lowest, highest DTM height under it) in terrain-relative mode];
    ``candidates``: GCP candidates [{"id", "x", "y", "z", "ground", "sx", "sy", "role"}, ...];
    ``render``: render settings that, when changed, must re-render (part of each tile's spec);
    ``terrain``: {"projection": "terrain" | "plane" | "paper", "dtm": path or None}. With
    "paper" the tiles lie on the paper camera's image plane (:func:`pipeline25d.camera.paper_affine`)
    with pixels of :func:`pipeline25d.camera.pixel_size`.
    """
    terrain = terrain or {"projection": "plane", "dtm": None}
    relative = terrain["projection"] == "terrain"
    camera = camera_of(terrain["projection"])
    pixel = pixel_size(gsd, p, camera)
    span = tile_span(pixel, tile_size)
    tiles: dict[tuple[int, int], dict] = {}
    for chunk in chunks:
        box, depth = projected_box(np.array(chunk["bounds"]), p, z0, chunk["ground"][:2] if relative else None, camera)
        entry = {"id": chunk["id"], "district": chunk["district"],
                 "lod": choose_level(chunk["errors"], max_error_px * gsd),
                 "xy": [round(float(v), 3) for v in (*chunk["bounds"][0][:2], *chunk["bounds"][1][:2])]}
        if "hash" in chunk:
            entry["hash"] = chunk["hash"]   # the chunk's LOD content: a changed chunk re-renders its tiles
        if relative:
            entry["ground"] = chunk["ground"][2]   # digest of the DTM under the chunk
        for r in _index_range(box.ymin, box.ymax, span):
            for c in _index_range(box.xmin, box.xmax, span):
                tile = tiles.setdefault((r, c), {"row": r, "col": c, "chunks": [], "depth_range": [math.inf, -math.inf],
                                                 "content": [math.inf, math.inf, -math.inf, -math.inf]})
                tile["chunks"].append(entry)
                tile["content"] = [min(tile["content"][0], box.xmin), min(tile["content"][1], box.ymin),
                                   max(tile["content"][2], box.xmax), max(tile["content"][3], box.ymax)]
                tile["depth_range"] = [min(tile["depth_range"][0], depth[0] - DEPTH_MARGIN_M),
                                       max(tile["depth_range"][1], depth[1] + DEPTH_MARGIN_M)]
    if not tiles:
        raise ValueError(f"{p.id}: no chunks to plan")
    _assign_gcps(tiles, candidates, p, z0, span, relative, camera)
    # everything a tile's pixels depend on beyond its own entry: a change re-renders it
    frame = {"z0": z0, "gsd": gsd, "tile_size": tile_size, "crs": crs, "perspective": p.id, **terrain}
    rows = [r for r, _ in tiles]
    cols = [c for _, c in tiles]
    total = (max(rows) - min(rows) + 1) * (max(cols) - min(cols) + 1)
    out_tiles = []
    for key in sorted(tiles, key=lambda k: (-k[0], k[1])):
        tile = tiles[key]
        tile["content"] = _content_in_tile(tile["content"], key, span, pixel)
        tile["chunks"].sort(key=lambda t: (t["district"], t["id"]))
        tile["render"] = render
        tile["spec_hash"] = hashlib.sha256(json.dumps([frame, tile], sort_keys=True).encode()).hexdigest()[:16]
        out_tiles.append(tile)
    return {
        "perspective": {"id": p.id, "azimuth": p.azimuth, "elevation": p.elevation},
        "crs": crs, "z0": z0, "gsd": gsd, "pixel_size": pixel, "tile_size": tile_size,
        "projection": terrain["projection"], "dtm": terrain["dtm"],
        "tiles": out_tiles,
        "n_tiles_total": total,
        "n_tiles_skipped": total - len(out_tiles),
    }


def _content_in_tile(box: list[float], key: tuple[int, int], span: float, pixel: float) -> list[float]:
    """The tile's share of its chunks' projected boxes, grown to whole pixels: where it can hold data."""
    r, c = key
    x0, y0 = max(box[0], c * span), max(box[1], r * span)
    x1, y1 = min(box[2], (c + 1) * span), min(box[3], (r + 1) * span)
    snap = [math.floor(x0 / pixel) * pixel, math.floor(y0 / pixel) * pixel,
            math.ceil(x1 / pixel) * pixel, math.ceil(y1 / pixel) * pixel]
    return [round(v, 6) for v in snap]


def _assign_gcps(tiles: dict, candidates: list[dict], p: Perspective, z0: float, span: float,
                 relative: bool, camera: str = "map") -> None:
    """Give each candidate to the tile holding its projected centre (if that tile exists)."""
    for tile in tiles.values():
        tile["gcps"] = []
    if not candidates:
        return
    xyz = np.array([[c["x"], c["y"], c["z"]] for c in candidates])
    if relative:
        m = project_above_ground(xyz, np.array([c["ground"] for c in candidates]), p)
    else:
        m = project(xyz, p, z0, camera)
    rows, cols = np.floor(m[:, 1] / span).astype(int), np.floor(m[:, 0] / span).astype(int)
    for cand, r, c in zip(candidates, rows, cols):
        if (r, c) in tiles:
            tiles[(r, c)]["gcps"].append({k: cand[k] for k in CANDIDATE_FIELDS})


@lru_cache(maxsize=256)
def _read_plan_cached(path: str, mtime_ns: int) -> dict:
    return json.loads(Path(path).read_text())


def read_plan(path: str | Path) -> dict:
    """A plan JSON, cached per file version (Snakemake asks once per render-block job)."""
    path = Path(path)
    return _read_plan_cached(str(path), path.stat().st_mtime_ns)


def block_of(row: int, col: int, block: int) -> tuple[int, int]:
    """The render block (block row, block col) holding tile (row, col): ``block`` x ``block`` tiles."""
    return row // block, col // block


def plan_blocks(plan: dict, block: int) -> dict[tuple[int, int], list[dict]]:
    """The plan's tiles grouped by render block, each block's tiles north row first (plan order)."""
    blocks: dict[tuple[int, int], list[dict]] = {}
    for tile in plan["tiles"]:
        blocks.setdefault(block_of(tile["row"], tile["col"], block), []).append(tile)
    return blocks


def plan_block(plan: dict, block_row: int, block_col: int, block: int) -> list[dict]:
    """The tiles of render block (block_row, block_col), grouped once per (cached) plan."""
    cache = plan.setdefault("_blocks", {})
    if block not in cache:
        cache[block] = plan_blocks(plan, block)
    if (block_row, block_col) not in cache[block]:
        raise KeyError(f"block ({block_row}, {block_col}) is not in the plan of {plan['perspective']['id']}")
    return cache[block][(block_row, block_col)]


def block_spec_hash(tiles: list[dict]) -> str:
    """One hash over a block's tiles and their spec hashes: changes when any of them does."""
    keys = [f"{t['row']}_{t['col']}:{t['spec_hash']}" for t in tiles]
    return hashlib.sha256("|".join(keys).encode()).hexdigest()[:16]
