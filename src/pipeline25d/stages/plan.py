"""Plan one perspective: the non-empty tiles, each with its chunks, LODs and GCPs.

Tiles lie on a global grid: tile (row, col) covers map x in [col·S, (col+1)·S) and y in
[row·S, (row+1)·S) with S = tile_size·gsd, so rows count northward. A tile's id and
extent therefore do not depend on the rest of the scene: adding or changing a district
leaves the other tiles' jobs untouched. A tile that no chunk's projected bounding box
overlaps (touching its edge is not enough) is empty and gets no job. Each tile carries its
own depth range (from its chunks), the GCP candidates whose projected centre it holds and
its content box (where its chunks' projected boxes meet it: nothing outside can be drawn).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections.abc import Mapping, Sequence
from functools import lru_cache
from pathlib import Path
from types import MappingProxyType

import numpy as np

from pipeline25d.core.atomic import write_json
from pipeline25d.core.errors import InputFileError
from pipeline25d.geometry.camera import (
    horizontal_direction,
    pixel_size,
    project,
    project_above_ground,
    projected_box,
    relief_factor,
)
from pipeline25d.geometry.perspectives import Perspective
from pipeline25d.stages.gcps import read_candidates
from pipeline25d.stages.lod import choose_level, lod_chunks
from pipeline25d.stages.records import (
    ChunkGround,
    GcpCandidate,
    LodChunk,
    Plan,
    Scene,
    Tile,
    camera_of,
    index_range,
    tile_span,
)
from pipeline25d.stages.scene import chunk_grounds, read_grounds

log = logging.getLogger(__name__)

DEPTH_MARGIN_M = 1.0   # keeps surfaces at a tile's depth range ends off its near/far planes


def plan_perspective(p: Perspective, chunks: Sequence[LodChunk], candidates: Sequence[GcpCandidate], z0: float,
                     gsd: float, tile_size: int, max_error_px: float, crs: str, render: dict,
                     terrain: dict | None = None, shadows: dict | None = None,
                     grounds: Mapping[tuple[str, str], ChunkGround] | None = None) -> Plan:
    """The plan of perspective ``p`` (its tiles' spec hashes are taken over their JSON form).

    ``chunks``: the LOD chunks; ``grounds``: the DTM under each, by (district, id) (terrain-relative maps);
    ``candidates``: the GCP candidates;
    ``render``: render settings that, when changed, must re-render (part of each tile's spec);
    ``terrain``: {"projection": "terrain" | "plane" | "paper", "dtm": path or None}. With
    "paper" the tiles lie on the paper camera's image plane (:func:`pipeline25d.geometry.camera.paper_affine`)
    with pixels of :func:`pipeline25d.geometry.camera.pixel_size`.
    ``shadows``: the resolved sun-shadow settings (:func:`pipeline25d.geometry.sun.plan_shadows`) or None;
    with them each tile also lists the chunks that can shadow what it draws (:func:`_add_shadows`).
    Without them the plan is exactly what it was before shadows existed.
    """
    terrain = terrain or {"projection": "plane", "dtm": None}
    relative = terrain["projection"] == "terrain"
    camera = camera_of(terrain["projection"])
    pixel = pixel_size(gsd, p, camera)
    span = tile_span(pixel, tile_size)
    tiles: dict[tuple[int, int], dict] = {}
    entries = []
    ground_of = (lambda c: grounds[(c.district, c.id)]) if relative else (lambda c: None)
    for chunk in chunks:
        ground = ground_of(chunk)
        box, depth = projected_box(np.array(chunk.bounds), p, z0, _ground_range(ground), camera)
        entry = {"id": chunk.id, "district": chunk.district,
                 "lod": choose_level(chunk.errors, max_error_px * gsd),
                 "xy": [round(float(v), 3) for v in (*chunk.bounds[0][:2], *chunk.bounds[1][:2])],
                 "hash": chunk.hash}   # the chunk's LOD content: a changed chunk re-renders its tiles
        if ground is not None:
            entry["ground"] = ground.digest   # digest of the DTM under the chunk
        entries.append(entry)
        for r in index_range(box.ymin, box.ymax, span):
            for c in index_range(box.xmin, box.xmax, span):
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
    for key, tile in tiles.items():
        tile["content"] = _content_in_tile(tile["content"], key, span, pixel)
    if shadows:
        frame["shadows"] = shadows
        _add_shadows(tiles, chunks, [ground_of(c) for c in chunks], entries, p, z0, camera, shadows)
    out_tiles = []
    for key in sorted(tiles, key=lambda k: (-k[0], k[1])):
        tile = tiles[key]
        tile["chunks"].sort(key=lambda t: (t["district"], t["id"]))
        tile["render"] = render
        tile["spec_hash"] = _digest([frame, tile])
        tile["image_hash"] = image_hash(frame, tile)
        out_tiles.append(tile)
    out = {
        "perspective": {"id": p.id, "azimuth": p.azimuth, "elevation": p.elevation},
        "crs": crs, "z0": z0, "gsd": gsd, "pixel_size": pixel, "tile_size": tile_size,
        "projection": terrain["projection"], "dtm": terrain["dtm"],
        "tiles": out_tiles,
        "n_tiles_total": total,
        "n_tiles_skipped": total - len(out_tiles),
    }
    if shadows:
        out["shadows"] = shadows
    return Plan.from_json(out)


def _add_shadows(tiles: dict, chunks: Sequence[LodChunk], grounds: list[ChunkGround | None], entries: list[dict],
                 p: Perspective, z0: float, camera: str, shadows: dict) -> None:
    """Give each tile its ``shadow``: the other chunks that can cast a shadow onto what it draws
    (their shadow footprints meet its receivers, see :mod:`pipeline25d.geometry.sun`), its shadow map's
    window on the global texel grid and its depth range (heights)."""
    from pipeline25d.geometry.sun import Sun, SunFrame, casters_of, shadow_footprints

    frame = SunFrame(Sun(shadows["azimuth"], shadows["elevation"]), shadows["texel"])
    bounds = np.array([c.bounds for c in chunks], dtype=np.float64)
    margin = frame.ground_margin()
    footprints = shadow_footprints(bounds, frame.sun, margin)
    index = {(c.district, c.id): i for i, c in enumerate(chunks)}
    for tile in tiles.values():
        own = [index[(e["district"], e["id"])] for e in tile["chunks"]]
        receivers = [box for i in own
                     if (box := _receiver_box(bounds[i], grounds[i], tile["content"], p, z0, camera)) is not None]
        receivers = receivers or [bounds[i] for i in own]
        hit = casters_of(footprints, receivers, margin)
        hit[own] = False
        others = np.flatnonzero(hit)
        tile["shadow"] = {
            "casters": sorted((entries[i] for i in others), key=lambda t: (t["district"], t["id"])),
            "window": list(frame.window(receivers)),
            "depth": [round(v, 3) for v in frame.depth_range([bounds[i] for i in (*own, *others)])],
        }


def _receiver_box(bounds: np.ndarray, ground: ChunkGround | None, content: list[float], p: Perspective, z0: float,
                  camera: str) -> np.ndarray | None:
    """(2, 3) box of the chunk's geometry that can land in a tile's ``content`` box (None: none can):
    a map point m comes from the ground point m − k·d, k = (z − reference)·cot φ over the chunk's heights.
    The paper camera's image is no map: the whole chunk box."""
    lo, hi = np.asarray(bounds, dtype=np.float64)
    if camera == "paper":
        return np.array([lo, hi])
    ref = _ground_range(ground) or (z0, z0)
    shifts = np.outer([(lo[2] - ref[1]), (hi[2] - ref[0])], horizontal_direction(p) * relief_factor(p))
    box = np.array([[max(content[0] - shifts[:, 0].max(), lo[0]), max(content[1] - shifts[:, 1].max(), lo[1]), lo[2]],
                    [min(content[2] - shifts[:, 0].min(), hi[0]), min(content[3] - shifts[:, 1].min(), hi[1]), hi[2]]])
    return box if (box[0, :2] <= box[1, :2]).all() else None


def _ground_range(ground: ChunkGround | None) -> tuple[float, float] | None:
    """(lowest, highest) DTM height under a chunk, or None (maps on a plane)."""
    return None if ground is None else (ground.lowest, ground.highest)


def _content_in_tile(box: list[float], key: tuple[int, int], span: float, pixel: float) -> list[float]:
    """The tile's share of its chunks' projected boxes, grown to whole pixels (at least one) within
    the tile: where it can hold data. Where it reaches a tile edge it takes that edge's very value,
    so neighbours' boxes meet exactly (snapping the edge itself can round a pixel past it)."""
    r, c = key
    out = []
    for lo, hi, i in ((box[0], box[2], c), (box[1], box[3], r)):
        start, end = i * span, (i + 1) * span
        a = max(math.floor(lo / pixel) * pixel, start)
        b = min(max(math.ceil(hi / pixel) * pixel, a + pixel), end)
        out.append((a, b))
    return [round(v, 6) for v in (out[0][0], out[1][0], out[0][1], out[1][1])]


def _assign_gcps(tiles: dict, candidates: Sequence[GcpCandidate], p: Perspective, z0: float, span: float,
                 relative: bool, camera: str = "map") -> None:
    """Give each candidate to the tile holding its projected centre (if that tile exists)."""
    for tile in tiles.values():
        tile["gcps"] = []
    if not candidates:
        return
    xyz = np.array([[c.x, c.y, c.z] for c in candidates])
    if relative:
        m = project_above_ground(xyz, np.array([c.ground for c in candidates]), p)
    else:
        m = project(xyz, p, z0, camera)
    rows, cols = np.floor(m[:, 1] / span).astype(int), np.floor(m[:, 0] / span).astype(int)
    for cand, r, c in zip(candidates, rows, cols):
        if (r, c) in tiles:
            tiles[(r, c)]["gcps"].append(cand.to_json())


@lru_cache(maxsize=256)
def _read_plan_cached(path: str, mtime_ns: int) -> Plan:
    try:
        return Plan.from_json(json.loads(Path(path).read_text()))
    except (ValueError, KeyError, TypeError) as exc:    # cut short or edited: the DAG cannot be built on it
        raise InputFileError(path, f"is not a readable plan ({type(exc).__name__}: {exc}); delete it to "
                             "plan this perspective again") from None


def read_plan(path: str | Path) -> Plan:
    """A plan file, read once per file version (Snakemake asks once per render-block job); a
    :class:`Plan` is immutable, so every caller may hold the same one."""
    path = Path(path)
    return _read_plan_cached(str(path), path.stat().st_mtime_ns)


@lru_cache(maxsize=64)
def _read_blocks_cached(path: str, mtime_ns: int, block: int) -> Mapping[str, tuple[Tile, ...]]:
    return MappingProxyType(plan_blocks(_read_plan_cached(path, mtime_ns), block))


def read_plan_blocks(path: str | Path, block: int) -> Mapping[str, tuple[Tile, ...]]:
    """:func:`plan_blocks` of a plan file, computed once per file version and block size."""
    path = Path(path)
    return _read_blocks_cached(str(path), path.stat().st_mtime_ns, block)


TILE_OVERHEAD = 0.25     # a tile's fixed cost (files, marker pass) in full tiles' pixels
TOP_LEVEL = 20           # the quadtree's roots: block x 2**20 tiles a side, more than any plan holds


def tile_cost(plan: Plan, tile: Tile) -> float:
    """A tile's render cost in pixels: its content box plus a fixed share of a whole tile."""
    _, (w, h) = plan.content(tile)
    return w * h + TILE_OVERHEAD * plan.tile_size ** 2


def plan_blocks(plan: Plan, block: int) -> dict[str, tuple[Tile, ...]]:
    """The plan's tiles grouped into render jobs, tiles in plan order (ids: :func:`block_node`).

    A quadtree over the tile grid: a node at level L holds the tiles of a square of
    ``block * 2**L`` tiles a side (rows and cols floor-divided, so it is fixed by position
    alone). A node whose tiles cost at most ``block`` x ``block`` whole tiles
    (:func:`tile_cost`) is one job ``"<level>_<row>_<col>"``. A costlier one splits into its
    four children, down to squares of ``block`` x ``block`` tiles: a child still too costly
    splits in turn, and the others, taken in Z order, are packed into jobs within that budget
    (``"<level>_<row>_<col>_<quadrants>"``). Dense land gets ``block`` x ``block`` squares;
    sparse land, where content boxes are small or tiles far apart, gets fewer, larger jobs.
    A change of content regroups only the nodes above it.
    """
    budget = block * block * (1 + TILE_OVERHEAD) * plan.tile_size ** 2
    costs = [tile_cost(plan, t) for t in plan.tiles]
    blocks: dict[str, list[int]] = {}

    def cost(members: list[int]) -> float:
        return sum(costs[i] for i in members)

    def visit(level: int, key: tuple[int, int], members: list[int]) -> None:
        if level == 0 or cost(members) <= budget:
            blocks[f"{level}_{key[0]}_{key[1]}"] = members
            return
        children = _group_by_node(plan, members, block << (level - 1))
        quadrant = {k: 2 * (k[0] - 2 * key[0]) + k[1] - 2 * key[1] for k in children}
        run: list[tuple[int, int]] = []          # the children packed so far, and their cost
        run_cost = 0.0

        def flush() -> None:
            if len(run) == 1:
                blocks[f"{level - 1}_{run[0][0]}_{run[0][1]}"] = children[run[0]]
            elif run:
                quadrants = "".join(str(quadrant[k]) for k in run)
                blocks[f"{level}_{key[0]}_{key[1]}_{quadrants}"] = sorted(i for k in run for i in children[k])
            run.clear()

        for child in sorted(children, key=quadrant.get):
            child_cost = cost(children[child])
            if child_cost > budget:
                flush()
                visit(level - 1, child, children[child])
                continue
            if run_cost + child_cost > budget:
                flush()
            if not run:
                run_cost = 0.0
            run.append(child)
            run_cost += child_cost
        flush()

    for key, members in _group_by_node(plan, range(len(plan.tiles)), block << TOP_LEVEL).items():
        visit(TOP_LEVEL, key, members)
    return {bid: tuple(plan.tiles[i] for i in members) for bid, members in blocks.items()}


def block_node(block_id: str, block: int) -> tuple[int, int, int, int, str]:
    """A block id's quadtree node: (first row, first col, side in tiles, level, quadrants taken:
    "" for the whole node)."""
    level, row, col, *quadrants = block_id.split("_")
    side = block << int(level)
    return int(row) * side, int(col) * side, side, int(level), "".join(quadrants)


def _group_by_node(plan: Plan, members, side: int) -> dict[tuple[int, int], list[int]]:
    """Tile indices grouped by the node of ``side`` x ``side`` tiles holding them, in plan order."""
    nodes: dict[tuple[int, int], list[int]] = {}
    for i in members:
        tile = plan.tiles[i]
        nodes.setdefault((tile.row // side, tile.col // side), []).append(i)
    return nodes


def plan_block(blocks: Mapping[str, tuple[Tile, ...]], block_id: str, plan_id: str) -> tuple[Tile, ...]:
    """The tiles of render block ``block_id`` among a plan's :func:`plan_blocks`."""
    if block_id not in blocks:
        raise KeyError(f"block {block_id} is not in the plan of {plan_id}")
    return blocks[block_id]


def _digest(value) -> str:
    return hashlib.sha256(json.dumps(value, sort_keys=True).encode()).hexdigest()[:16]


def image_hash(frame: dict, tile: dict) -> str:
    """The hash of what a tile's image (and object ids) depend on: its spec less its GCP candidates
    and the marker settings. A tile whose spec changed but not this keeps its image, and only its
    GCPs are observed again (:func:`pipeline25d.stages.render_block.render_block`)."""
    from pipeline25d.config import MARKER_SETTINGS

    image = {k: v for k, v in tile.items() if k not in ("gcps", "spec_hash", "image_hash")}
    image["render"] = {k: v for k, v in tile["render"].items() if k not in MARKER_SETTINGS}
    return _digest([frame, image])


def block_spec_hash(tiles: Sequence[Tile]) -> str:
    """One hash over a block's tiles and their spec hashes: changes when any of them does."""
    keys = [f"{t.row}_{t.col}:{t.spec_hash}" for t in tiles]
    return hashlib.sha256("|".join(keys).encode()).hexdigest()[:16]


def plans(out_plans: Mapping[str, str | Path], lod_indexes: list[str], scene_json: str | Path,
          candidates_csv: str | Path, gsd: float, tile_size: int, max_error_px: float, crs: str, render: dict,
          work: dict | None = None, grounds_json: str | Path | None = None) -> list[Plan]:
    """Plan each perspective id of ``out_plans`` into its file (see :mod:`pipeline25d.stages.plan`), in
    one process: the scene, the chunks, their grounds and the GCP candidates are read once (one job
    for all views: one start-up and one Snakemake checkpoint, whose every completion re-evaluates
    the DAG). ``render`` holds render + marker settings, and the ``shadows`` block when shadows are
    enabled (:func:`pipeline25d.config.render_settings`). ``work``
    (:func:`pipeline25d.stages.budget.settings`): each map's estimated pixels and tiles are checked
    against its limits before any perspective is planned. ``grounds_json``: the scene stage's DTM
    under each chunk (:func:`pipeline25d.stages.scene.write_grounds`); without it, in
    terrain-relative mode, they are sampled here."""
    from pipeline25d.core.raster import DTM
    from pipeline25d.geometry.sun import plan_shadows
    from pipeline25d.stages import budget

    scene = Scene.read(scene_json)
    if work is not None:
        for perspective_id in out_plans:
            budget.check_perspective(work, Perspective.from_id(perspective_id), np.array(scene.bounds))
    render = dict(render)
    shadow_cfg = render.pop("shadows", None)
    shadows = plan_shadows(shadow_cfg, np.array(scene.bounds), crs, gsd) if shadow_cfg else None
    relative = scene.projection == "terrain"
    chunks = lod_chunks(lod_indexes)
    grounds = None
    if relative and grounds_json is not None:
        grounds = read_grounds(grounds_json)
    elif relative:
        grounds = chunk_grounds(chunks, DTM(scene.dtm, crs, continuous=True))
    terrain = {"projection": scene.projection, "dtm": scene.dtm if relative else None}
    candidates = read_candidates(candidates_csv)
    results = []
    for perspective_id, out_plan in out_plans.items():
        result = plan_perspective(Perspective.from_id(perspective_id), chunks, candidates, scene.z0, gsd, tile_size,
                                  max_error_px, crs, render, terrain, shadows, grounds)
        write_json(out_plan, result.to_json(), indent=None)   # megabytes for a city: compact
        log.info("%s: %d tiles to render, %d empty tiles skipped", perspective_id, len(result.tiles),
                 result.n_tiles_skipped)
        if shadows:
            log.info("%s: sun at azimuth %.2f°, elevation %.2f° (%s); %d shadow casters from other tiles' chunks",
                     perspective_id, shadows["azimuth"], shadows["elevation"], shadows["source"],
                     sum(len(t.casters) for t in result.tiles))
        results.append(result)
    return results
