"""The render job: one block of a perspective's tiles in one process and GL context.

A tile's files (GeoTIFF, its object ids where ``objects.enabled``, GCPs seen, spec and image
hashes) are written atomically, hashes last: a tile whose ``.spec`` matches its plan entry (and
which has its ids tile where ids are asked for) is complete and kept, so a changed district
re-renders only its own tiles. One whose image hash alone matches (its GCP candidates changed,
not what it draws) keeps its image and observes its GCPs again.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import write_json
from pipeline25d.core.grid import Extent
from pipeline25d.geometry.perspectives import Perspective
from pipeline25d.stages.gcps import OBSERVATION_FIELDS, observations, write_csv
from pipeline25d.stages.lod import load_chunk_level
from pipeline25d.stages.plan import plan_block, read_plan, read_plan_blocks
from pipeline25d.stages.records import ChunkRef, Observation, Plan, Tile

log = logging.getLogger(__name__)


# an id tile: uint32, nodata 0; ZSTD level 1 writes it ~4x faster than DEFLATE, and smaller
ID_OPTIONS = ("COMPRESS=ZSTD", "ZSTD_LEVEL=1", "PREDICTOR=2", "TILED=YES")


def tile_files(tiles_dir: str | Path, row: int, col: int) -> dict[str, Path]:
    """A tile's files: its RGBA GeoTIFF, its object ids (uint32 GeoTIFF on the same grid, 0: none),
    the GCPs seen in it, and the spec hash it was rendered for."""
    base = Path(tiles_dir) / f"{row}_{col}"
    return {"gcps": Path(f"{base}.gcps.csv"), "tif": Path(f"{base}.tif"), "ids": Path(f"{base}.ids.tif"),
            "spec": Path(f"{base}.spec")}


def _tile_state(tiles_dir: str | Path, tile: Tile, objects: bool) -> str:
    """"current" if the tile's files exist (its ids tile where ``objects``) and were rendered for
    its spec hash; "image" if only its GCPs are not (its image files were rendered for its image
    hash: only its spec's GCP part changed); else "none". The spec file holds both hashes."""
    files = tile_files(tiles_dir, tile.row, tile.col)
    needed = [f for k, f in files.items() if k != "ids" or objects]
    if not all(f.exists() for f in needed):
        return "none"
    spec, image = (files["spec"].read_text().split() + ["", ""])[:2]
    return "current" if spec == tile.spec_hash else "image" if tile.image_hash and image == tile.image_hash else "none"


def render_block(plan_path: str | Path, block_id: str, block: int, lod_dir: str | Path, tiles_dir: str | Path,
                 out_manifest: str | Path, objects: bool = True, workers: int | None = None) -> dict:
    """Render the tiles of one render block (:func:`~pipeline25d.stages.plan.plan_blocks`) in one process
    and GL context.

    Each tile gets its own files (:func:`tile_files`), written GCPs, GeoTIFF, then spec hash,
    each atomically: a tile whose ``.spec`` matches its plan entry is complete and is kept as
    it is, so a changed district re-renders only its own tiles even though its block job runs
    again. A tile whose image hash still matches (only its GCP candidates or the marker
    settings changed: another perspective added, a new ``gcp.spacing``, with a DTM that does
    not move with the check points) keeps its image and gets only its marker pass again.
    ``objects``: each tile also gets its object ids (:mod:`.render_ids`), drawn by the colour
    pass itself (a second render target). The manifest (written last) lists the block's tiles, how
    many were rendered and how many only observed their GCPs again. ``workers``: the cores the job
    may use now (one: a software rasterizer draws in the job's thread,
    :func:`~pipeline25d.stages.render.create_context`).
    """
    from pipeline25d.stages.render import TileRenderer, create_context
    from pipeline25d.stages.render_ids import IdRenderer

    pl = read_plan(plan_path)
    tiles = plan_block(read_plan_blocks(plan_path, block), block_id, pl.id)
    state = {t.key: _tile_state(tiles_dir, t, objects) for t in tiles}
    todo = [t for t in tiles if state[t.key] != "current"]
    if todo:
        chunks = ChunkCache(lod_dir, todo, shaded={t.key for t in todo if state[t.key] == "none"})
        ground = _block_ground(pl, todo)
        ctx = create_context(workers)
        try:
            renderer = TileRenderer(ctx, ambient=todo[0].render["ambient"], samples=todo[0].render["samples"],
                                    shadows=pl.shadows is not None, ids=objects)
            id_renderer = IdRenderer(ctx, samples=todo[0].render["samples"]) if objects else None
            for k, tile in enumerate(todo, 1):
                image = state[tile.key] == "none"
                casters = chunks.take(tile.casters) if pl.shadows is not None and image else None
                rgba, seen, ids = render_plan_tile(renderer, pl, tile, chunks.take(tile.chunks), ground, casters,
                                                   id_renderer, image=image)
                _write_tile(pl, tile, rgba, seen, tiles_dir, ids)
                log.info("%s tile %d_%d (%d of %d): %s, GCPs seen %d of %d", pl.id, tile.row, tile.col, k,
                         len(todo), f"coverage {100 * float((rgba[..., 3] > 0).mean()):.1f}%" if image else
                         "image kept", len(seen), len(tile.gcps))
        finally:
            ctx.release()
    rendered = sum(state[t.key] == "none" for t in tiles)
    manifest = {"perspective": pl.id, "block": block_id,
                "tiles": [{"row": t.row, "col": t.col, "spec_hash": t.spec_hash} for t in tiles],
                "rendered": rendered, "gcps_only": len(todo) - rendered, "kept": len(tiles) - len(todo),
                "objects": bool(objects)}
    write_json(out_manifest, manifest)
    log.info("block %s: %d tiles rendered, %d only observed their GCPs again, %d unchanged kept", block_id,
             rendered, len(todo) - rendered, len(tiles) - len(todo))
    return manifest


class ChunkCache:
    """Chunk LODs loaded once per block job and dropped after the last tile that draws them.
    ``shaded``: the keys of the tiles whose shadow casters are taken too (None: all)."""

    def __init__(self, lod_dir: str | Path, tiles: Sequence[Tile], shaded: set[str] | None = None):
        from collections import Counter

        self.lod_dir = Path(lod_dir)
        self.uses = Counter(self._key(c) for t in tiles
                            for c in (*t.chunks, *(t.casters if shaded is None or t.key in shaded else ())))
        self.loaded: dict[tuple, tuple[np.ndarray, list]] = {}

    @staticmethod
    def _key(chunk: ChunkRef) -> tuple:
        return chunk.district, chunk.id, chunk.lod

    def take(self, entries: Sequence[ChunkRef]) -> list[tuple[np.ndarray, list]]:
        """The loaded chunks of plan ``entries`` (a tile's chunks or its shadow casters)."""
        out = []
        for c in entries:
            key = self._key(c)
            if key not in self.loaded:
                self.loaded[key] = load_chunk_level(self.lod_dir / c.district / f"{c.id}.npz", c.lod)
            out.append(self.loaded[key])
            self.uses[key] -= 1
            if not self.uses[key]:
                del self.loaded[key]
        return out


def _block_ground(pl: Plan, tiles: Sequence[Tile]):
    """DTM(x, y) around what the tiles draw (their chunks' and GCPs' ground extent), read once per
    block; None in plane mode."""
    from pipeline25d.core.raster import DTM

    if pl.projection != "terrain":
        return None
    return DTM(pl.dtm, pl.crs, continuous=True, window=ground_window(tiles)).sample


def ground_window(tiles: Sequence[Tile]) -> Extent:
    """The scene-CRS extent whose ground ``tiles`` sample: their chunks' extents and their GCPs."""
    xy = [np.array(c.xy).reshape(2, 2) for t in tiles for c in t.chunks]
    xy += [np.array([[c.x, c.y] for c in t.gcps]).reshape(-1, 2) for t in tiles]
    xy = np.concatenate(xy)
    return Extent(*xy.min(axis=0), *xy.max(axis=0))


def render_plan_tile(renderer, pl: Plan, tile: Tile, chunks: list, ground, casters: list | None = None,
                     id_renderer=None, image: bool = True) -> tuple[np.ndarray | None, list[Observation],
                                                                   np.ndarray | None]:
    """(RGBA image, GCP observations, object ids or None) of one plan tile from its loaded chunks;
    ``ground`` = DTM(x, y) in terrain-relative mode, else None; ``casters``: its loaded shadow
    casters (plans with shadows); ``id_renderer``: an :class:`~.render_ids.IdRenderer` for the
    tile's ids (None: none), drawn by the colour pass as a second render target. ``image``
    False: the GCP observations alone (the same), no colour pass (image and ids None)."""
    from pipeline25d.stages.render import TileView, marker_images
    from pipeline25d.stages.render_ids import part_face_ids

    persp, t, gsd, cfg = pl.perspective, pl.tile_size, pl.gsd, tile.render
    depth = tuple(tile.depth_range)
    camera, pixel = pl.camera, pl.pixel_size
    content, size = pl.content(tile)          # where its chunks can draw: the tile or less
    view = TileView(persp, pl.z0, content, depth, size, ground, camera)
    rgba = ids = None
    with renderer.upload(chunks, view) as geometry:          # once for both passes
        if image and id_renderer is None:
            rgba = renderer.render_color(geometry, view, shadow_view(pl, tile), casters)
        elif image:     # one pass: the ids are a second render target of the colour pass
            rgba, ids = id_renderer.with_colour(renderer, geometry, view, part_face_ids, shadow_view(pl, tile), casters)
        seen = []
        if tile.gcps:
            margin, radius = int(np.ceil(cfg["marker_px"])) + 2, cfg["marker_px"] * gsd
            pts = np.array([[c.x, c.y, c.z] for c in tile.gcps])
            slopes = np.array([[c.sx, c.sy] for c in tile.gcps])
            view = TileView(persp, pl.z0, pl.tile_extent(tile.row, tile.col, margin), depth,
                            (t + 2 * margin, t + 2 * margin), ground, camera)
            extent, size = marker_window(view, *marker_images(pts, slopes, radius, view))
            view = TileView(persp, pl.z0, extent, depth, size, ground, camera)
            full, sums = renderer.render_markers(geometry, view, pts, slopes, radius,
                                                 cfg["depth_bias"],
                                                 marker_depth_tolerance(persp, gsd, cfg["max_float_px"]))
            seen = observations(tile.gcps, full, sums, (extent.xmin, extent.ymax), pixel)
    return rgba, seen, ids


def marker_window(view, centres: np.ndarray, reach: np.ndarray) -> tuple[Extent, tuple[int, int]]:
    """The part of a tile's marker ``view`` that holds its markers' images (centres and reach from
    :func:`~pipeline25d.stages.render.marker_images`), in whole pixels of the view's grid: the
    marker pass draws only there (a tile's edge or a sparse one draws a fraction of its pixels)."""
    e, (w, h) = view.extent, view.size
    px = e.width / w
    lo, hi = (centres - reach[:, None]).min(axis=0), (centres + reach[:, None]).max(axis=0)
    c0, c1 = min(max(math.floor((lo[0] - e.xmin) / px), 0), w - 1), min(math.ceil((hi[0] - e.xmin) / px), w)
    r0, r1 = min(max(math.floor((e.ymax - hi[1]) / px), 0), h - 1), min(math.ceil((e.ymax - lo[1]) / px), h)
    c1, r1 = max(c1, c0 + 1), max(r1, r0 + 1)
    return Extent(e.xmin + c0 * px, e.ymax - r1 * px, e.xmin + c1 * px, e.ymax - r0 * px), (c1 - c0, r1 - r0)


def shadow_view(pl: Plan, tile: Tile):
    """The tile's :class:`~pipeline25d.stages.render.ShadowView` from its plan, or None without shadows."""
    from pipeline25d.geometry.sun import Sun, SunFrame
    from pipeline25d.stages.render import ShadowView

    s = pl.shadows
    if not s:
        return None
    frame = SunFrame(Sun(s["azimuth"], s["elevation"]), s["texel"])
    return ShadowView(frame, tuple(tile.shadow.window), tuple(tile.shadow.depth), s["ambient"], s["bias"], s["radius"])


def _write_tile(pl: Plan, tile: Tile, rgba: np.ndarray | None, seen: list[Observation], tiles_dir: str | Path,
                ids: np.ndarray | None = None) -> None:
    """GCPs, GeoTIFF, its ids (or none: a stale ids tile removed), then the spec and image hashes
    that mark the tile complete (see :func:`render_block`). ``rgba`` None: the image files are
    kept as they are (rendered for the tile's image hash), its GCPs alone are written."""
    from pipeline25d.core.atomic import write_text
    from pipeline25d.core.crs import horizontal_wkt
    from pipeline25d.core.geotiff import write_geotiff, write_rgba_geotiff

    files = tile_files(tiles_dir, tile.row, tile.col)
    files["spec"].unlink(missing_ok=True)
    # the paper camera's tiles lie on its image plane, which is no CRS: the warp georeferences them
    wkt = "" if pl.camera == "paper" else horizontal_wkt(pl.crs)
    write_csv(files["gcps"], seen, OBSERVATION_FIELDS)
    if rgba is not None:
        write_rgba_geotiff(files["tif"], rgba, pl.tile_grid(tile), wkt)
        if ids is None:
            files["ids"].unlink(missing_ok=True)
        else:
            write_geotiff(files["ids"], ids, pl.tile_grid(tile), wkt, "UInt32", ID_OPTIONS, nodata=0)
    write_text(files["spec"], f"{tile.spec_hash} {tile.image_hash}\n")


def marker_depth_tolerance(p: Perspective, gsd: float, max_float_px: float) -> float:
    """View-depth gap (m) between a marker and the surface under it that shifts its image by max_float_px.

    A marker δ metres above the ground appears δ·cot φ from that ground on the map and
    δ / sin φ nearer in depth: the tolerance is max_float_px·gsd / cos φ (unbounded at nadir).
    """
    if p.elevation == 90:
        return math.inf
    return max_float_px * gsd / math.cos(math.radians(p.elevation))
