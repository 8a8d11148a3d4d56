"""The terrain stage's job: the scene's DSM and, with ``terrain: auto``, its ground cells (the inputs'
own terrain, else their buildings' bases and CSF)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import write_json
from pipeline25d.core.errors import GroundError
from pipeline25d.core.mesh import Mesh
from pipeline25d.stages.lod import chunk_loaders, scene_bounds
from pipeline25d.stages.records import LodChunk

log = logging.getLogger(__name__)

DSM_LOD_CELLS = 0.25      # the DSM is rendered from the coarsest LOD within this many cells of error


def build_terrain(chunks: Sequence[LodChunk], inputs: dict, scene_crs: str, gsd: float, terrain: str,
                  ground_cfg: dict, out_dsm: str | Path, out_ground: str | Path | None, out_json: str | Path,
                  processes: int = 1) -> dict:
    """Render the DSM of the LOD ``chunks``; with ``terrain: auto`` also find its ground cells
    (see :mod:`pipeline25d.stages.terrain`).

    ``out_ground`` holds the ground heights (NaN elsewhere); the scene stage interpolates
    the DTM from it once it knows the check points, which it holds out of the DTM. Both
    rasters are written block by block: memory follows a block, not the scene. ``processes``:
    how many DSM render tiles and ground-filter blocks run at once (the same rasters whatever the count).
    """
    from pipeline25d.core.cores import fork_pool
    from pipeline25d.core.crs import horizontal_wkt
    from pipeline25d.core.geotiff import float_geotiff_writer
    from pipeline25d.core.grid import Grid
    from pipeline25d.stages.terrain.dsm import auto_resolution, dsm_tiles, height_map_tiles
    from pipeline25d.stages.terrain.ground import ground_layout

    _, lo, hi = scene_bounds(chunks)
    bounds_xy = (lo[0], lo[1], hi[0], hi[1])
    res = ground_cfg["resolution"]
    res = auto_resolution(bounds_xy, gsd) if res == "auto" else float(res)
    grid = Grid.covering(bounds_xy, res)
    log.info("DSM: %d x %d cells of %.2f m from %d chunks", grid.width, grid.height, res, len(chunks))
    wkt = horizontal_wkt(scene_crs)
    dsm_cells = 0
    with ExitStack() as stack:
        # workers where the DSM's render tiles or the ground filter's blocks can be shared, forked before
        # the DSM render makes this job large
        blocks = terrain == "auto" and len(ground_layout(grid, ground_cfg["max_object_size"],
                                                         cloth_resolution(ground_cfg, res))) > 1
        several = processes > 1 and (blocks or len(dsm_tiles(grid)) > 1)
        pool = stack.enter_context(fork_pool(processes)) if several else None
        with float_geotiff_writer(out_dsm, grid, wkt) as write:
            for row, col, heights in height_map_tiles(chunk_loaders(chunks, DSM_LOD_CELLS * res), grid, pool=pool,
                                                      ahead=processes):
                write(heights, row, col)
                dsm_cells += int(np.isfinite(heights).sum())
        record = {"dsm": str(out_dsm), "resolution": res, "dsm_cells": dsm_cells}
        if terrain == "auto":
            record.update(_ground_from_model(inputs, scene_crs, ground_cfg, out_dsm, out_ground, wkt, processes, pool,
                                             chunks=chunks))
            log.info("ground from %s: %.1f%% of the model's cells, relief %.1f m", record["source"],
                     100 * record["ground_share"], record["relief_m"])
    if terrain == "flat":
        record.update({"source": "flat plane at z0"})
    elif terrain != "auto":
        record.update({"source": f"user DTM {terrain}", "dtm": terrain})
    write_json(out_json, record)
    return record


def cloth_resolution(ground_cfg: dict, res: float) -> float:
    """The Cloth Simulation Filter's grid (m): the config's, or twice the DSM's cells (auto)."""
    cloth = ground_cfg["cloth_resolution"]
    return 2 * res if cloth == "auto" else float(cloth)


def _ground_from_model(inputs: dict, scene_crs: str, ground_cfg: dict, dsm_path: str | Path,
                       out_ground: str | Path, wkt: str, processes: int = 1, pool=None,
                       chunks: Sequence[LodChunk] = ()) -> dict:
    """Write the ground heights on the DSM's grid, block by block: the inputs' own terrain where
    they carry one; elsewhere the bases of their buildings (:mod:`pipeline25d.stages.terrain.bases`;
    in a format without building objects, those found by their shape in an input of buildings
    alone: :mod:`pipeline25d.stages.terrain.shapes`) and, unless every other input is made of
    buildings alone, the Cloth Simulation Filter's ground cells of the DSM
    (:func:`~pipeline25d.stages.terrain.bases.with_bases` joins the two)."""
    from pipeline25d.core.geotiff import FloatRaster, float_geotiff_writer
    from pipeline25d.core.grid import cell_blocks
    from pipeline25d.stages.terrain.bases import district_bases, with_bases
    from pipeline25d.stages.terrain.dsm import render_height_map
    from pipeline25d.stages.terrain.ground import ground_blocks
    from pipeline25d.stages.terrain.shapes import buildings_by_shape

    dsm_src = FloatRaster(dsm_path)
    grid = dsm_src.grid
    own = _own_terrain(inputs, scene_crs)

    def by_shape(name: str) -> tuple[Mesh, bool] | None:   # at the LOD the DSM was rendered from
        own_chunks = [c for c in chunks if c.district == name]
        found = buildings_by_shape(chunk_loaders(own_chunks, DSM_LOD_CELLS * grid.res), dsm_src)
        alone = found.buildings and not found.others
        log.log(logging.INFO if found.groups else logging.DEBUG,
                "%s: %d of %d groups of triangles are buildings by their shape, %.0f of %.0f m² seen from above "
                "are not; %d chunks draw their own ground: %s", name, found.buildings, found.groups,
                found.others_seen_m2, found.seen_m2, found.ground_chunks,
                "buildings alone, their bases give the ground" if alone else "the filter finds its ground")
        return (found.mesh, False) if alone else None

    bases = district_bases(inputs, scene_crs, own["districts"], 2 * ground_cfg["max_object_size"], by_shape)
    sources = []
    if set(inputs) - set(own["districts"]) - set(bases.buildings_only):
        cloth = cloth_resolution(ground_cfg, grid.res)
        blocks = ground_blocks(dsm_src.read, grid, ground_cfg["max_object_size"], cloth, ground_cfg["rigidness"],
                               ground_cfg["class_threshold"], processes=processes, pool=pool,
                               iterations=ground_cfg["cloth_iterations"])
        sources.append("model surface (nadir DSM, Cloth Simulation Filter)")
    else:
        blocks = ((b, dsm_src.read(*b.core), np.zeros(grid.window(*b.core).shape, bool))
                  for b in cell_blocks(grid.height, grid.width, 0))
    if bases.tin is not None:
        sources.append(bases.describe())
    if own["districts"]:
        sources.append("the inputs' own terrain (CityJSON/CityGML TINRelief or ground objects) of "
                       + ", ".join(own["districts"]))
    n_valid, n_ground, n_base, zmin, zmax = 0, 0, 0, np.inf, -np.inf
    with float_geotiff_writer(out_ground, grid, wkt) as write:
        for block, dsm, ground in blocks:
            seed = np.where(ground, dsm, np.nan)
            if bases.tin is not None:
                base = bases.tin.heights(grid.window(*block.core))
                n_base += int(np.isfinite(base).sum())
                seed = with_bases(seed, base)
            if own["chunks"]:
                heights = render_height_map(own["chunks"], grid.window(*block.core))
                have = np.isfinite(heights)
                seed[have] = heights[have]
            write(seed, block.core[0].start, block.core[1].start)
            has = np.isfinite(seed)
            n_valid, n_ground = n_valid + int(np.isfinite(dsm).sum()), n_ground + int(has[np.isfinite(dsm)].sum())
            if has.any():
                zmin, zmax = min(zmin, float(seed[has].min())), max(zmax, float(seed[has].max()))
        if zmax < zmin:
            raise GroundError(f"terrain: auto found no ground in the model ({', '.join(sorted(inputs))}: "
                              "no terrain of their own, no buildings' bases, no ground the Cloth Simulation "
                              "Filter could find); give a DTM (terrain: <path>) or terrain: flat")
    record = {"source": " + ".join(sources), "ground": str(out_ground),
              "ground_share": n_ground / n_valid if n_valid else 0.0, "relief_m": zmax - zmin}
    if bases.tin is not None:
        record["bases"] = {**bases.record(), "cells": n_base}
    return record


def _own_terrain(inputs: dict, scene_crs: str) -> dict:
    """The inputs' own terrain (e.g. CityJSON/CityGML TINRelief / ground objects): the districts carrying
    one and their meshes as (bounds, load) chunks for :func:`pipeline25d.stages.terrain.dsm.render_height_map`."""
    from pipeline25d.formats import load_district_terrain
    from pipeline25d.stages.chunks import chunk_origin

    districts, chunks = [], []
    for name, spec in sorted(inputs.items()):
        mesh = load_district_terrain(spec, scene_crs)
        if mesh is None or not mesh.n_triangles:
            continue
        districts.append(name)
        b = mesh.bounds()
        chunks.append((b, lambda b=b, parts=mesh.parts: (chunk_origin(b), parts)))
    return {"districts": districts, "chunks": chunks}
