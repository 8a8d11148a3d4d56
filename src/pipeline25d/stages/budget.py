"""The work a config asks for, estimated before anything is made in proportion to it, and the
limits (config key ``limits``) it must stay under.

A typo such as ``gsd: 0.00001`` asks for about 10¹⁵ map pixels of a 700 m scene; the plan would
try to list billions of tiles and take the machine down. :func:`estimate` computes, from the
scene's extent (x, y, z bounds in the scene CRS) and the config alone, in O(perspectives):

* map pixels per perspective: the scene box projected by the perspective's camera, over the
  pixel size squared (what :mod:`pipeline25d.stages.plan` covers with tiles);
* tiles per perspective: the cells of the global tile grid that box overlaps (an upper bound
  of the non-empty tiles a plan lists), and the render jobs they make at most;
* chunks: the cells of the chunk grid over the extent (an upper bound of the chunks ingest makes);
* terrain cells: the DSM/DTM grid at ``ground.resolution`` (or the cloth grid, if finer);
* bytes written, at most: every render tile, every map and the web pyramid over it (4/3 of the
  maps' pixels, all zoom levels) at 4 bytes (RGBA) a pixel, and with ``objects.enabled`` every
  render tile's and map's object ids at 4 bytes (uint32) more, before compression. Compression makes
  the real figure smaller (zstd render tiles and COGs, webp tiles: about 2 to 3 times on a
  textured city); the bound is what a disk must be ready for.

:func:`check` refuses work beyond a limit with one paragraph: what was asked, the limit, the
key that raises it and the likely cause. It runs at parse time when the extent is cheaply known
(:mod:`pipeline25d.stages.extent`), in the terrain job (the first job that knows every chunk),
and in each plan job before any tile is listed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline25d.core.errors import ConfigError
from pipeline25d.core.grid import Grid
from pipeline25d.geometry.camera import pixel_size, projected_box
from pipeline25d.geometry.perspectives import Perspective, expand
from pipeline25d.stages.records import LodChunk, camera_of, index_range, tile_span

#: the schema's defaults, for callers without a validated config (the plan stage's tests)
DEFAULT_LIMITS = {"max_map_pixels": 1.0e10, "max_tiles": 200_000, "max_chunks": 100_000,
                  "max_terrain_cells": 2.5e8, "max_output_bytes": 1.0e12}
BYTES_PER_PIXEL = 4          # RGBA, before compression
PYRAMID = 4 / 3              # a web pyramid's pixels over its finest level's


@dataclass(frozen=True)
class Work:
    """What a config asks for over one extent. ``map_pixels`` and ``tiles`` are per perspective id."""

    extent: tuple[float, float, float, float, float, float]   # xmin, ymin, zmin, xmax, ymax, zmax
    source: str                                               # where the extent was read
    map_pixels: dict[str, float]
    tiles: dict[str, int]
    render_jobs: int
    chunks: int
    terrain_cells: int
    tile_size: int
    ids: bool = False                                         # object ids beside tiles and maps

    @property
    def total_pixels(self) -> float:
        return float(sum(self.map_pixels.values()))

    @property
    def output_bytes(self) -> float:
        """At most this many bytes written: render tiles, maps, web pyramid and object ids (module docstring)."""
        rendered = sum(self.tiles.values()) * self.tile_size ** 2
        return BYTES_PER_PIXEL * ((1 + self.ids) * rendered + (1 + self.ids + PYRAMID) * self.total_pixels)

    def summary(self) -> str:
        """``9 maps, 2.3e+08 px, 1350 tiles (about 90 render jobs), 36 chunks, 5.2e+05 terrain cells,
        at most 2.1 GB written``."""
        return (f"{len(self.map_pixels)} maps, {self.total_pixels:.2g} px, {sum(self.tiles.values())} tiles "
                f"(about {self.render_jobs} render jobs), {self.chunks} chunks, {self.terrain_cells:.2g} terrain "
                f"cells, at most {self.output_bytes / 1e9:.3g} GB written")


def settings(config: dict[str, Any]) -> dict[str, Any]:
    """What :func:`estimate` and :func:`check` read of a validated config (a rule's params)."""
    from pipeline25d.config import chunk_size, objects_enabled

    return {"gsd": config["gsd"], "tile_size": config["tile_size"], "perspectives": config["perspectives"],
            "projection": config["projection"], "block": config["render"]["block"], "chunk_size": chunk_size(config),
            "ground": {k: config["ground"][k] for k in ("resolution", "cloth_resolution")},
            "objects": objects_enabled(config),
            "limits": dict(config["limits"])}


def perspective_work(p: Perspective, extent: np.ndarray, gsd: float, tile_size: int,
                     projection: str) -> tuple[float, int]:
    """(map pixels, tiles) of perspective ``p`` over the (2, 3) ``extent``: its projected box (with
    z0 at the extent's floor, which moves the box but does not change its size) over the pixel."""
    camera = camera_of(projection)
    pixel = pixel_size(gsd, p, camera)
    box, _ = projected_box(extent, p, float(extent[0][2]), None, camera)
    span = tile_span(pixel, tile_size)
    pixels = max(box.width, pixel) * max(box.height, pixel) / pixel ** 2
    return pixels, len(index_range(box.xmin, box.xmax, span)) * len(index_range(box.ymin, box.ymax, span))


def terrain_resolution(ground: dict[str, Any], extent_xy: tuple[float, float, float, float], gsd: float) -> float:
    """The finest grid the terrain stage makes: the DSM at ``ground.resolution`` (auto: the
    terrain stage's own rule), or the cloth grid where it is given finer."""
    from pipeline25d.stages.terrain.dsm import auto_resolution

    res = auto_resolution(extent_xy, gsd) if ground["resolution"] == "auto" else float(ground["resolution"])
    cloth = ground.get("cloth_resolution", "auto")
    return res if cloth == "auto" else min(res, float(cloth))


def estimate(work: dict[str, Any], extent: np.ndarray, source: str) -> Work:
    """The work ``work`` (:func:`settings`) asks for over the (2, 3) ``extent`` read from ``source``."""
    extent = np.asarray(extent, dtype=np.float64)
    (x0, y0, z0), (x1, y1, z1) = extent
    pixels, tiles = {}, {}
    for p in expand(work["perspectives"]):
        pixels[p.id], tiles[p.id] = perspective_work(p, extent, work["gsd"], work["tile_size"], work["projection"])
    block = work["block"]
    render_jobs = sum(math.ceil(n / block ** 2) for n in tiles.values())
    res = terrain_resolution(work["ground"], (x0, y0, x1, y1), work["gsd"])
    grid = Grid.covering((x0, y0, x1, y1), res)            # the grid the terrain stage makes
    cells = grid.width * grid.height
    size = float(work["chunk_size"])
    chunks = len(index_range(x0, x1, size)) * len(index_range(y0, y1, size))
    return Work((x0, y0, z0, x1, y1, z1), source, pixels, tiles, render_jobs, chunks, cells, work["tile_size"],
                bool(work.get("objects", False)))


def check(work: dict[str, Any], found: Work) -> None:
    """Raise ConfigError when ``found`` passes a limit of ``work["limits"]``: what was asked, the
    limit, the key that raises it and the likely cause."""
    limits = {**DEFAULT_LIMITS, **work.get("limits", {})}
    x0, y0, _, x1, y1, _ = found.extent
    scene = f"a {x1 - x0:.4g} × {y1 - y0:.4g} m scene"
    at_default = found.total_pixels * (work["gsd"] / 0.25) ** 2 / max(len(found.map_pixels), 1)
    gsd_typo = f"Is gsd {work['gsd']:g} m a typo? At 0.25 m a map of this scene has {at_default:.2g} px."
    worst = max(found.map_pixels, key=found.map_pixels.get)
    most_tiles = max(found.tiles, key=found.tiles.get)
    problems = [
        (found.map_pixels[worst], "max_map_pixels",
         f"gsd {work['gsd']:g} m on {scene} asks for {len(found.map_pixels)} maps of up to "
         f"{found.map_pixels[worst]:.2g} pixels ({worst}; {found.total_pixels:.2g} in all)", gsd_typo),
        (found.tiles[most_tiles], "max_tiles",
         f"tile_size {work['tile_size']} px at gsd {work['gsd']:g} m on {scene} asks for "
         f"{found.tiles[most_tiles]} tiles in one map ({most_tiles})", f"Is tile_size too small? {gsd_typo}"),
        (found.chunks, "max_chunks", f"chunk_size {work['chunk_size']:g} m on {scene} asks for up to {found.chunks} "
         "chunks", "Is chunk_size a typo? (auto: 400·gsd, at least 100 m)"),
        (found.terrain_cells, "max_terrain_cells",
         f"the terrain grid (ground.resolution {work['ground']['resolution']}, cloth_resolution "
         f"{work['ground'].get('cloth_resolution', 'auto')}) on {scene} has {found.terrain_cells:.2g} cells",
         "Is ground.resolution or ground.cloth_resolution a typo? (auto: 2·gsd, 0.5 to 5 m)"),
        (found.output_bytes, "max_output_bytes",
         f"gsd {work['gsd']:g} m on {scene} writes up to {found.output_bytes:.2g} bytes (render tiles, "
         f"{len(found.map_pixels)} maps and their web pyramids, before compression)", gsd_typo),
    ]
    for value, key, asked, cause in problems:
        if value > limits[key]:
            raise ConfigError(f"config key limits.{key}: {asked}, beyond the limit of {limits[key]:.3g} (scene "
                              f"extent from {found.source}). {cause} If the work is meant, raise limits.{key} "
                              "in the config.")


def check_ingested(work: dict[str, Any], chunks: Sequence[LodChunk]) -> Work:
    """:func:`check` over the ingested chunks' extent (the terrain job, before any grid is made)."""
    from pipeline25d.stages.lod import scene_bounds

    _, lo, hi = scene_bounds(chunks)
    found = estimate(work, np.array([lo, hi]), "the ingested chunks")
    check(work, found)
    return found


def check_perspective(work: dict[str, Any], p: Perspective, extent: np.ndarray) -> None:
    """:func:`check` of one perspective's map over ``extent`` (the plan job, before any tile is listed)."""
    one = {**work, "perspectives": [{"azimuth": p.azimuth, "elevation": p.elevation}]}
    check(one, estimate(one, extent, "the ingested chunks"))
