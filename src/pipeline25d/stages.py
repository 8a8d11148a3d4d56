"""One function per workflow stage: pure functions of their input files and parameters.

The Snakemake rules (workflow/rules/*.smk) call these through thin scripts or
``python -m pipeline25d``; tests call them directly.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np

from .atomic import write_json
from .errors import ConfigError
from .chunks import content_hash, load_npz, pack_parts, save_npz, unpack_parts
from .gcps import CANDIDATE_FIELDS, OBSERVATION_FIELDS, assign_roles, observations, read_csv, write_csv
from .ingest import write_chunks
from .lod import build_levels
from .mesh import Mesh
from .perspectives import Perspective
from .plan import (extent_geotransform, plan_block, plan_camera, plan_perspective, plan_pixel, read_plan,
                   tile_content, tile_extent)

log = logging.getLogger(__name__)

GROUND_MARGIN_M = 2.0   # widens a chunk's ground range (tile assignment in terrain mode) against sampling gaps


# -- ingest / lod --------------------------------------------------------------------------
def ingest(spec: dict, district: str, scene_crs: str, chunk_size: float, max_geometric_error: float,
           index_path: str | Path, gsd: float | None = None) -> dict:
    """Read one district and write its chunks beside ``index_path``."""
    from .formats import load_district

    mesh = load_district(spec, scene_crs, max_geometric_error=max_geometric_error, gsd=gsd)
    log.info("%s: %d triangles from %s", district, mesh.n_triangles, spec["path"])
    index_path = Path(index_path)
    return write_chunks(mesh, district, chunk_size, index_path.parent, index_path)


def build_lod(chunk_index: str | Path, out_index: str | Path, max_error: float, max_levels: int) -> dict:
    """Write the LOD pyramid of every chunk of a district beside ``out_index``, then the index.

    ``chunk_index``: the district's ingest index (its chunk npz files beside it). One npz per
    chunk (:func:`build_chunk_lod`); a chunk whose ingest hash and LOD parameters are those of
    the previous run keeps its file (and mtime), so no tile drawing it re-runs. The previous
    run's entries live in ``index.hashes.json``, which is no declared output: Snakemake deletes
    the index itself before the job. Files of chunks no longer in the district are removed.
    Returns the index: {district, max_error, max_levels, chunks: {id: {bounds, errors, triangles, hash}}}.
    """
    chunk_index, out_index = Path(chunk_index), Path(out_index)
    ingested = json.loads(chunk_index.read_text())
    params = {"max_error": max_error, "max_levels": max_levels}
    sidecar = out_index.with_suffix(".hashes.json")
    kept = _reusable_lods(sidecar, params, ingested["chunks"], out_index.parent)
    write_json(sidecar, {"params": params, "chunks": kept})   # before any npz is rewritten: no false record survives a crash
    record = {}
    for cid, info in sorted(ingested["chunks"].items()):
        record[cid] = kept.get(cid) or {"source": info["hash"], **build_chunk_lod(
            chunk_index.parent / f"{cid}.npz", out_index.parent / f"{cid}.npz", max_error, max_levels)}
    _remove_stale_lods(out_index.parent, record)
    write_json(sidecar, {"params": params, "chunks": record})
    index = {"district": ingested["district"], **params,
             "chunks": {cid: {k: v for k, v in r.items() if k != "source"} for cid, r in record.items()}}
    write_json(out_index, index)
    log.info("%s: %d chunk LODs built, %d unchanged", ingested["district"], len(record) - len(kept), len(kept))
    return index


def _reusable_lods(sidecar: Path, params: dict, chunks: dict[str, dict], out_dir: Path) -> dict[str, dict]:
    """The previous run's entries {id: {"source": ingest hash, ...}} still valid for ``chunks``."""
    if not sidecar.exists():
        return {}
    previous = json.loads(sidecar.read_text())
    if previous.get("params") != params:
        return {}
    return {cid: entry for cid, entry in previous["chunks"].items()
            if cid in chunks and entry["source"] == chunks[cid]["hash"] and (out_dir / f"{cid}.npz").exists()}


def _remove_stale_lods(out_dir: Path, keep: dict) -> None:
    """Remove LOD npz files of chunks not in ``keep``, and the per-chunk JSON of the former layout."""
    for path in [*out_dir.glob("c*.npz"), *out_dir.glob("c*.json")]:
        if path.suffix == ".json" or path.stem not in keep:
            path.unlink()


def build_chunk_lod(chunk_path: str | Path, out_npz: str | Path, max_error: float, max_levels: int) -> dict:
    """Write the LOD pyramid of one chunk (npz); returns its {bounds, errors, triangles, hash}."""
    data = load_npz(chunk_path)
    origin = data["origin"]
    mesh = Mesh(unpack_parts(data, origin), source=str(chunk_path))
    levels = build_levels(mesh, max_error=max_error, max_levels=max_levels)
    arrays = {"origin": origin, "n_levels": np.array(len(levels))}
    for k, (parts, _) in enumerate(levels):
        arrays.update(pack_parts(parts, origin, prefix=f"L{k}_"))
    save_npz(out_npz, arrays)
    return {"bounds": mesh.bounds().tolist(), "errors": [e for _, e in levels],
            "triangles": [sum(p.n_triangles for p in ps) for ps, _ in levels], "hash": content_hash(arrays)}


def lod_chunks(lod_indexes: list[str | Path]) -> list[dict]:
    """Every chunk of the given district LOD indexes, in their order then by id:
    {"id", "district", "bounds", "errors", "triangles", "hash", "npz" (its LOD file)}."""
    out = []
    for path in lod_indexes:
        index = json.loads(Path(path).read_text())
        out += [{"id": cid, "district": index["district"], **entry, "npz": str(Path(path).parent / f"{cid}.npz")}
                for cid, entry in sorted(index["chunks"].items())]
    return out


def load_chunk_level(lod_npz: str | Path, level: int) -> tuple[np.ndarray, list]:
    data = load_npz(lod_npz)
    origin = data["origin"]
    level = min(level, int(data["n_levels"]) - 1)
    return origin, unpack_parts(data, origin, prefix=f"L{level}_")


# -- terrain: DSM from the model, DTM from the model (terrain: auto) ----------------------------
def _lod_chunk_loaders(chunks: list[dict], max_error: float) -> list[tuple[np.ndarray, object]]:
    """(bounds, load) per chunk of :func:`lod_chunks`; load() -> (origin, parts) at the coarsest
    LOD within ``max_error`` m."""
    from functools import partial

    from .lod import choose_level

    return [(np.array(c["bounds"]), partial(load_chunk_level, c["npz"], choose_level(c["errors"], max_error)))
            for c in chunks]


def _scene_bounds(chunks: list[dict]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every chunk's bounds (n, 2, 3) and the scene's lowest and highest corners."""
    bounds = np.array([c["bounds"] for c in chunks])
    return bounds, bounds[:, 0].min(axis=0), bounds[:, 1].max(axis=0)


def build_terrain(lod_indexes: list[str], inputs: dict, scene_crs: str, gsd: float, terrain: str, ground_cfg: dict,
                  out_dsm: str | Path, out_ground: str | Path | None, out_json: str | Path) -> dict:
    """Render the scene's DSM; with ``terrain: auto`` also find its ground cells (see :mod:`pipeline25d.terrain`).

    ``out_ground`` holds the ground heights (NaN elsewhere); the scene stage interpolates
    the DTM from it once it knows the check points, which it holds out of the DTM. Both
    rasters are written block by block: memory follows a block, not the scene.
    """
    from .crs import horizontal_wkt
    from .terrain import Grid, auto_resolution, float_geotiff_writer, height_map_tiles

    chunks = lod_chunks(lod_indexes)
    _, lo, hi = _scene_bounds(chunks)
    bounds_xy = (lo[0], lo[1], hi[0], hi[1])
    res = ground_cfg["resolution"]
    res = auto_resolution(bounds_xy, gsd) if res == "auto" else float(res)
    grid = Grid.covering(bounds_xy, res)
    log.info("DSM: %d x %d cells of %.2f m from %d chunks", grid.width, grid.height, res, len(chunks))
    wkt = horizontal_wkt(scene_crs)
    dsm_cells = 0
    with float_geotiff_writer(out_dsm, grid, wkt) as write:
        for row, col, heights in height_map_tiles(_lod_chunk_loaders(chunks, res / 4), grid):
            write(heights, row, col)
            dsm_cells += int(np.isfinite(heights).sum())
    record = {"dsm": str(out_dsm), "resolution": res, "dsm_cells": dsm_cells}
    if terrain == "auto":
        record.update(_ground_from_model(inputs, scene_crs, ground_cfg, out_dsm, out_ground, wkt))
        log.info("ground from %s: %.1f%% of the model's cells, relief %.1f m", record["source"],
                 100 * record["ground_share"], record["relief_m"])
    elif terrain == "flat":
        record.update({"source": "flat plane at z0"})
    else:
        record.update({"source": f"user DTM {terrain}", "dtm": terrain})
    write_json(out_json, record)
    return record


def _ground_from_model(inputs: dict, scene_crs: str, ground_cfg: dict, dsm_path: str | Path,
                       out_ground: str | Path, wkt: str) -> dict:
    """Write the ground heights on the DSM's grid, block by block: the inputs' own terrain where
    they carry one, the Cloth Simulation Filter's ground cells of the DSM elsewhere."""
    from .terrain import FloatRaster, cell_blocks, float_geotiff_writer, ground_blocks, render_height_map

    dsm_src = FloatRaster(dsm_path)
    grid = dsm_src.grid
    own = _own_terrain(inputs, scene_crs)
    sources = []
    if own["districts"] != sorted(inputs):
        cloth = ground_cfg["cloth_resolution"]
        cloth = 2 * grid.res if cloth == "auto" else float(cloth)
        blocks = ground_blocks(dsm_src.read, grid, ground_cfg["max_object_size"], cloth, ground_cfg["rigidness"],
                               ground_cfg["class_threshold"])
        sources.append("model surface (nadir DSM, Cloth Simulation Filter)")
    else:
        blocks = ((b, dsm_src.read(*b.core), np.zeros(grid.window(*b.core).shape, bool))
                  for b in cell_blocks(grid.height, grid.width, 0))
    if own["districts"]:
        sources.append("the inputs' own terrain (CityJSON/CityGML TINRelief or ground objects) of "
                       + ", ".join(own["districts"]))
    n_valid, n_ground, zmin, zmax = 0, 0, np.inf, -np.inf
    with float_geotiff_writer(out_ground, grid, wkt) as write:
        for block, dsm, ground in blocks:
            seed = np.where(ground, dsm, np.nan)
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
            raise ValueError("terrain: auto found no ground in the model; give a DTM (terrain: <path>) "
                             "or terrain: flat")
    return {"source": " + ".join(sources), "ground": str(out_ground),
            "ground_share": n_ground / n_valid if n_valid else 0.0, "relief_m": zmax - zmin}


def _own_terrain(inputs: dict, scene_crs: str) -> dict:
    """The inputs' own terrain (e.g. CityJSON/CityGML TINRelief / ground objects): the districts carrying
    one and their meshes as (bounds, load) chunks for :func:`pipeline25d.terrain.render_height_map`."""
    from .chunks import chunk_origin
    from .formats import load_district_terrain

    districts, chunks = [], []
    for name, spec in sorted(inputs.items()):
        mesh = load_district_terrain(spec, scene_crs)
        if mesh is None or not mesh.n_triangles:
            continue
        districts.append(name)
        b = mesh.bounds()
        chunks.append((b, lambda b=b, parts=mesh.parts: (chunk_origin(b), parts)))
    return {"districts": districts, "chunks": chunks}


# -- scene: reference plane and GCP candidates --------------------------------------------------
def scene_setup(lod_indexes: list[str], dsm_path: str | Path, terrain: str, terrain_path: str | Path | None,
                z0_cfg, projection: str, gcp_cfg: dict, scene_crs: str, gsd: float, perspective_ids: list[str],
                out_scene: str | Path, out_candidates: str | Path, out_dtm: str | Path | None = None,
                max_object_size: float = 100.0) -> dict:
    """Reference plane z0, projection mode, GCP candidates (with check-point roles) and, for
    ``terrain: auto``, the DTM.

    ``terrain_path``: the ground heights from :func:`build_terrain` (auto) or the user's DTM.
    With auto, the ground around each check point (within :func:`holdout_radius`) is left
    out of the DTM's interpolation, so a check point measures how well the DTM predicts
    ground it has not seen, not the DSM against itself.

    Memory: the DSM and the DTM are held whole as float32, 8 bytes a cell, which loses
    nothing (the DSM is read from its float32 GeoTIFF, GDAL's fill computes in float32);
    the DTM's interpolation and the site search run block by block.
    """
    from .crs import horizontal_wkt
    from .gcp_sites import SiteRules, select_sites
    from .gcps import candidates_from_sites
    from .raster import DTM
    from .terrain import FloatRaster, write_float_geotiff

    chunks = lod_chunks(lod_indexes)
    bounds, lo, hi = _scene_bounds(chunks)
    dsm_src = FloatRaster(dsm_path)
    grid = dsm_src.grid
    dsm = dsm_src.read_all(np.float32)
    seed_src, radius, height_fn = None, None, None
    search = int(np.ceil(max_object_size / 2 / grid.res))
    if terrain == "flat":
        level = float(z0_cfg) if z0_cfg != "auto" else float(np.median(bounds[:, 0, 2]))
        dtm = np.broadcast_to(level, grid.shape)
    elif terrain == "auto":
        seed_src = FloatRaster(terrain_path)
        needed = _under_chunks(bounds, grid)
        dtm = _interpolated_dtm(seed_src.read, grid, search, needed)
    else:
        height_fn = DTM(terrain_path, scene_crs, continuous=True).sample
        dtm = _sampled_dtm(height_fn, grid)
    covered = np.isfinite(dsm)
    # auto: the median ground height, rounded to whole metres so a local terrain change does not move it
    z0 = float(z0_cfg) if z0_cfg != "auto" else float(round(_median(dtm[covered]))) if covered.any() else float(lo[2])
    if projection == "auto":
        projection = "plane" if terrain == "flat" else "terrain"
    if projection == "terrain" and terrain == "flat":
        raise ConfigError("config key projection: terrain-relative projection needs a terrain (auto or a DTM path), "
                          "not terrain: flat")
    perspectives = [Perspective.from_id(pid) for pid in perspective_ids]
    if gcp_cfg["source"] == "auto":
        rules = SiteRules(spacing=gcp_cfg["spacing"], radius=gcp_cfg["marker_px"] * gsd,
                          clearance=gcp_cfg["clearance"], max_height=gcp_cfg["max_height"],
                          max_roughness=gcp_cfg["max_roughness"], max_slope=gcp_cfg["max_slope"])
        cands = candidates_from_sites(select_sites(dsm, dtm, grid, rules, perspectives),
                                      gcp_cfg["holdout"], gcp_cfg["seed"])
        if seed_src is not None:
            radius = holdout_radius(rules, grid.res)
            del dtm
            dtm = _interpolated_dtm(lambda rows, cols: _without_check_points(seed_src.read(rows, cols), grid, cands,
                                                                              radius, (rows, cols)), grid, search,
                                   needed)
            xy = np.array([[c["x"], c["y"]] for c in cands]).reshape(-1, 2)
            for c, g in zip(cands, _sample_continuous(dtm, grid, xy)):
                c["ground"] = round(float(g), 3)
            log.info("DTM interpolated without the ground within %.1f m of each check point", radius)
    else:
        rows = read_csv(gcp_cfg["source"])
        xy = np.array([[r["x"], r["y"]] for r in rows]).reshape(-1, 2)
        ground = (height_fn(xy[:, 0], xy[:, 1]) if height_fn else
                  np.array([_cell_value(dtm, grid, x, y) for x, y in xy]))
        cands = assign_roles([{"id": r["id"], "x": r["x"], "y": r["y"], "z": r["z"], "ground": float(g),
                               "sx": 0.0, "sy": 0.0} for r, g in zip(rows, ground)],
                             gcp_cfg["holdout"], gcp_cfg["seed"])
    if terrain == "auto":
        write_float_geotiff(out_dtm, dtm, grid, horizontal_wkt(scene_crs))
    dtm_path = out_dtm if terrain == "auto" else terrain_path
    scene = {"bounds": [lo.tolist(), hi.tolist()], "z0": z0, "terrain": terrain, "projection": projection,
             "dtm": None if terrain == "flat" else str(dtm_path),
             "n_candidates": len(cands), "n_check": sum(c["role"] == "check" for c in cands),
             "dtm_check_holdout_m": radius,
             "n_chunks": len(chunks)}
    write_csv(out_candidates, cands, CANDIDATE_FIELDS)
    write_json(out_scene, scene)
    log.info("z0 %.2f m, projection %s, %d GCP candidates (%d check points)", z0, projection, len(cands),
             scene["n_check"])
    return scene


def _interpolated_dtm(read, grid, search: int, needed=None) -> np.ndarray:
    """The DTM (float32, exact: GDAL's fill computes in float32) from the ground heights ``read(rows, cols)``.

    With ``needed`` (a sparse scene's blocks under the model), the DTM reaches 4 x ``search``
    cells (twice the largest object) beyond the ground and is NaN elsewhere: empty land costs nothing.
    """
    from .terrain import dtm_blocks

    dtm = np.empty(grid.shape, np.float32)
    reach = None if needed is None else 4 * search
    for block, values in dtm_blocks(read, grid, search, needed=needed, reach_cells=reach):
        dtm[block.core] = values
    return dtm


def _under_chunks(bounds: np.ndarray, grid, margin_cells: int = 2):
    """``needed(core)``: whether a block's cells (widened by ``margin_cells``) meet a chunk's footprint.

    The DTM is sampled only under the model's chunks, so blocks of empty land (a sparse
    scene) need none.
    """
    xy = np.asarray(bounds, dtype=np.float64)[:, :, :2]      # (n, 2 [lo, hi], 2 [x, y])

    def needed(core: tuple[slice, slice]) -> bool:
        rows, cols = core
        pad = margin_cells * grid.res
        x0, x1 = grid.xmin + cols.start * grid.res - pad, grid.xmin + cols.stop * grid.res + pad
        y1, y0 = grid.ymax - rows.start * grid.res + pad, grid.ymax - rows.stop * grid.res - pad
        return bool(np.any((xy[:, 0, 0] <= x1) & (xy[:, 1, 0] >= x0) & (xy[:, 0, 1] <= y1) & (xy[:, 1, 1] >= y0)))

    return needed


def _sampled_dtm(height_fn, grid, rows_per_strip: int = 256) -> np.ndarray:
    """A user DTM sampled at every cell centre, a strip of rows at a time."""
    dtm = np.empty(grid.shape)
    xs, ys = grid.column_x(), grid.row_y()
    for r0 in range(0, grid.height, rows_per_strip):
        gx, gy = np.meshgrid(xs, ys[r0:r0 + rows_per_strip])
        dtm[r0:r0 + rows_per_strip] = height_fn(gx.ravel(), gy.ravel()).reshape(gx.shape)
    return dtm


def _median(values: np.ndarray) -> float:
    """np.median of a (float32) vector in float64, partitioning ``values`` in place (no copy)."""
    n = len(values)
    values.partition([(n - 1) // 2, n // 2])
    return (float(values[(n - 1) // 2]) + float(values[n // 2])) / 2


def _sample_continuous(values: np.ndarray, grid, xy: np.ndarray) -> np.ndarray:
    """Bilinear heights at (n, 2) points, as ``DTM.from_array(values, continuous=True)`` gives them,
    each from the few cells around it (no float64 copy of the grid)."""
    from .raster import DTM

    out = np.empty(len(xy))
    for i, (x, y) in enumerate(xy):
        col = min(max(int((x - grid.xmin) / grid.res), 0), grid.width - 1)
        row = min(max(int((grid.ymax - y) / grid.res), 0), grid.height - 1)
        rows, cols = slice(max(row - 2, 0), min(row + 3, grid.height)), slice(max(col - 2, 0), min(col + 3, grid.width))
        window = DTM.from_array(values[rows, cols], grid.window(rows, cols).geotransform, continuous=True)
        out[i] = window.sample(np.array([x]), np.array([y]))[0]
    return out


def holdout_radius(rules, res: float) -> float:
    """Metres of ground around a check point left out of the DTM: its marker, the marker's
    clearance and two DTM cells, so the DTM must predict the whole marker from ground it saw
    farther away. (Wider holes would degrade the DTM, and so the maps, wherever check points
    are dense: on Delft's LiDAR mesh, 5 m holes round check points 4 m apart made the ground
    of the oblique maps 2-3 times farther off, as image correlation measures it.)"""
    return rules.radius + rules.clearance + 2 * res


def _without_check_points(seed: np.ndarray, grid, cands: list[dict], radius: float,
                          window: tuple[slice, slice] | None = None) -> np.ndarray:
    """A copy of the ground heights with the cells within ``radius`` of each check point set to NaN.

    ``window``: ``seed`` holds only these (rows, cols) of ``grid``.
    """
    out = seed.copy()
    rows, cols = window or (slice(0, grid.height), slice(0, grid.width))
    xs, ys = grid.column_x(), grid.row_y()
    k = int(np.ceil(radius / grid.res)) + 1
    for c in cands:
        if c["role"] != "check":
            continue
        col, row = int((c["x"] - grid.xmin) / grid.res), int((grid.ymax - c["y"]) / grid.res)
        r0, r1 = max(row - k, rows.start), min(row + k + 1, rows.stop)
        c0, c1 = max(col - k, cols.start), min(col + k + 1, cols.stop)
        if r0 >= r1 or c0 >= c1:
            continue
        near = np.hypot(xs[None, c0:c1] - c["x"], ys[r0:r1, None] - c["y"]) <= radius
        out[r0 - rows.start:r1 - rows.start, c0 - cols.start:c1 - cols.start][near] = np.nan
    return out


def _cell_value(values: np.ndarray, grid, x: float, y: float) -> float:
    """The value of the grid cell holding (x, y), clamped to the grid."""
    col = min(max(int((x - grid.xmin) / grid.res), 0), grid.width - 1)
    row = min(max(int((grid.ymax - y) / grid.res), 0), grid.height - 1)
    return float(values[row, col])


def chunk_ground(bounds: np.ndarray, dtm) -> list:
    """[lowest, highest, digest] of the DTM under a chunk's footprint.

    Heights are sampled every DTM cell (at most 129 × 129) and widened by GROUND_MARGIN_M;
    the digest of the samples enters the tile spec, so a tile re-renders when, and only
    when, the ground under one of its chunks changes.
    """
    import hashlib

    lo, hi = np.asarray(bounds, dtype=np.float64)
    step = abs(dtm.gt[1])
    nx = int(min(max(np.ceil((hi[0] - lo[0]) / step) + 1, 2), 129))
    ny = int(min(max(np.ceil((hi[1] - lo[1]) / step) + 1, 2), 129))
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], nx), np.linspace(lo[1], hi[1], ny))
    g = dtm.sample(gx.ravel(), gy.ravel())
    if not np.isfinite(g).all() or np.abs(g).max() > 1e5:
        raise ValueError(f"{dtm.path}: DTM heights under the chunk at {lo[:2]}..{hi[:2]} are not finite "
                         "or not plausible (|h| > 100 km)")
    digest = hashlib.sha256(np.round(g, 2).tobytes()).hexdigest()[:12]   # cm: float noise does not count
    return [float(np.min(g)) - GROUND_MARGIN_M, float(np.max(g)) + GROUND_MARGIN_M, digest]


# -- plan ---------------------------------------------------------------------------------
def plan(perspective_id: str, lod_indexes: list[str], scene_json: str | Path, candidates_csv: str | Path,
         gsd: float, tile_size: int, max_error_px: float, crs: str, render: dict, out_plan: str | Path) -> dict:
    """Plan one perspective (see :mod:`pipeline25d.plan`); ``render`` holds render + marker settings,
    and the ``shadows`` block when shadows are enabled (:func:`pipeline25d.config.render_settings`)."""
    from .raster import DTM
    from .sun import plan_shadows

    scene = json.loads(Path(scene_json).read_text())
    render = dict(render)
    shadow_cfg = render.pop("shadows", None)
    shadows = plan_shadows(shadow_cfg, np.array(scene["bounds"]), crs, gsd) if shadow_cfg else None
    relative = scene["projection"] == "terrain"
    dtm = DTM(scene["dtm"], crs, continuous=True) if relative else None
    chunks = [{**{k: c[k] for k in ("id", "district", "bounds", "errors", "hash")},
               "ground": chunk_ground(c["bounds"], dtm) if relative else None} for c in lod_chunks(lod_indexes)]
    terrain = {"projection": scene["projection"], "dtm": scene["dtm"] if relative else None}
    result = plan_perspective(Perspective.from_id(perspective_id), chunks, read_csv(candidates_csv),
                              scene["z0"], gsd, tile_size, max_error_px, crs, render, terrain, shadows)
    write_json(out_plan, result, indent=None)   # megabytes for a city: compact
    log.info("%s: %d tiles to render, %d empty tiles skipped", perspective_id, len(result["tiles"]),
             result["n_tiles_skipped"])
    if shadows:
        log.info("%s: sun at azimuth %.2f°, elevation %.2f° (%s); %d shadow casters from other tiles' chunks",
                 perspective_id, shadows["azimuth"], shadows["elevation"], shadows["source"],
                 sum(len(t["shadow"]["casters"]) for t in result["tiles"]))
    return result


# -- render -------------------------------------------------------------------------------
def tile_files(tiles_dir: str | Path, row: int, col: int) -> dict[str, Path]:
    """A tile's files: its RGBA GeoTIFF, the GCPs seen in it, and the spec hash it was rendered for."""
    base = Path(tiles_dir) / f"{row}_{col}"
    return {"gcps": Path(f"{base}.gcps.csv"), "tif": Path(f"{base}.tif"), "spec": Path(f"{base}.spec")}


def _tile_current(tiles_dir: str | Path, tile: dict) -> bool:
    """True if the tile's files exist and were rendered for its current spec hash."""
    files = tile_files(tiles_dir, tile["row"], tile["col"])
    return all(f.exists() for f in files.values()) and files["spec"].read_text().strip() == tile["spec_hash"]


def render_block(plan_path: str | Path, block_id: str, block: int, lod_dir: str | Path, tiles_dir: str | Path,
                 out_manifest: str | Path) -> dict:
    """Render the tiles of one render block (:func:`~pipeline25d.plan.plan_blocks`) in one process and GL context.

    Each tile gets its own files (:func:`tile_files`), written GCPs, GeoTIFF, then spec hash,
    each atomically: a tile whose ``.spec`` matches its plan entry is complete and is kept as
    it is, so a changed district re-renders only its own tiles even though its block job runs
    again. The manifest (written last) lists the block's tiles and which were rendered.
    """
    from .render import TileRenderer, create_context

    pl = read_plan(plan_path)
    tiles = plan_block(pl, block_id, block)
    todo = [t for t in tiles if not _tile_current(tiles_dir, t)]
    if todo:
        chunks = _ChunkCache(lod_dir, todo)
        ground = _block_ground(pl, todo)
        ctx = create_context()
        try:
            renderer = TileRenderer(ctx, ambient=todo[0]["render"]["ambient"], samples=todo[0]["render"]["samples"],
                                    shadows="shadows" in pl)
            for k, tile in enumerate(todo, 1):
                casters = chunks.take(_casters(tile)) if "shadows" in pl else None
                rgba, seen = render_plan_tile(renderer, pl, tile, chunks.take(tile["chunks"]), ground, casters)
                _write_tile(pl, tile, rgba, seen, tiles_dir)
                log.info("%s tile %d_%d (%d of %d): coverage %.1f%%, GCPs seen %d of %d", pl["perspective"]["id"],
                         tile["row"], tile["col"], k, len(todo), 100 * float((rgba[..., 3] > 0).mean()),
                         len(seen), len(tile["gcps"]))
        finally:
            ctx.release()
    manifest = {"perspective": pl["perspective"]["id"], "block": block_id,
                "tiles": [{"row": t["row"], "col": t["col"], "spec_hash": t["spec_hash"]} for t in tiles],
                "rendered": len(todo), "kept": len(tiles) - len(todo)}
    write_json(out_manifest, manifest)
    log.info("block %s: %d tiles rendered, %d unchanged kept", block_id, len(todo),
             len(tiles) - len(todo))
    return manifest


class _ChunkCache:
    """Chunk LODs loaded once per block job and dropped after the last tile that draws them."""

    def __init__(self, lod_dir: str | Path, tiles: list[dict]):
        from collections import Counter

        self.lod_dir = Path(lod_dir)
        self.uses = Counter(self._key(c) for t in tiles for c in (*t["chunks"], *_casters(t)))
        self.loaded: dict[tuple, tuple[np.ndarray, list]] = {}

    @staticmethod
    def _key(chunk: dict) -> tuple:
        return chunk["district"], chunk["id"], chunk["lod"]

    def take(self, entries: list[dict]) -> list[tuple[np.ndarray, list]]:
        """The loaded chunks of plan ``entries`` (a tile's chunks or its shadow casters)."""
        out = []
        for c in entries:
            key = self._key(c)
            if key not in self.loaded:
                self.loaded[key] = load_chunk_level(self.lod_dir / c["district"] / f"{c['id']}.npz", c["lod"])
            out.append(self.loaded[key])
            self.uses[key] -= 1
            if not self.uses[key]:
                del self.loaded[key]
        return out


def _casters(tile: dict) -> list[dict]:
    """The other tiles' chunks that can shadow what a tile draws (none without shadows)."""
    return tile.get("shadow", {}).get("casters", [])


def _block_ground(pl: dict, tiles: list[dict]):
    """DTM(x, y) around what the tiles draw (their chunks' and GCPs' ground extent), read once per
    block; None in plane mode."""
    from .raster import DTM

    if pl.get("projection") != "terrain":
        return None
    xy = [np.array(c["xy"]).reshape(2, 2) for t in tiles for c in t["chunks"]]
    xy += [np.array([[c["x"], c["y"]] for c in t["gcps"]]).reshape(-1, 2) for t in tiles]
    xy = np.concatenate(xy)
    return DTM(pl["dtm"], pl["crs"], continuous=True, window=(*xy.min(axis=0), *xy.max(axis=0))).sample


def render_plan_tile(renderer, pl: dict, tile: dict, chunks: list, ground,
                     casters: list | None = None) -> tuple[np.ndarray, list[dict]]:
    """(RGBA image, GCP observations) of one plan tile from its loaded chunks; ``ground`` = DTM(x, y)
    in terrain-relative mode, else None; ``casters``: its loaded shadow casters (plans with shadows)."""
    from .render import TileView

    row, col = tile["row"], tile["col"]
    persp = Perspective.from_id(pl["perspective"]["id"])
    t, gsd, cfg = pl["tile_size"], pl["gsd"], tile["render"]
    depth = tuple(tile["depth_range"])
    camera, pixel = plan_camera(pl), plan_pixel(pl)
    content, size = tile_content(pl, tile)          # where its chunks can draw: the tile or less
    view = TileView(persp, pl["z0"], content, depth, size, ground, camera)
    with renderer.upload(chunks, view) as geometry:          # once for both passes
        rgba = renderer.render_color(geometry, view, shadow_view(pl, tile), casters)
        seen = []
        if tile["gcps"]:
            margin = int(np.ceil(cfg["marker_px"])) + 2
            extent = tile_extent(pl, row, col, margin)
            view = TileView(persp, pl["z0"], extent, depth, (t + 2 * margin, t + 2 * margin), ground, camera)
            pts = np.array([[c["x"], c["y"], c["z"]] for c in tile["gcps"]])
            slopes = np.array([[c["sx"], c["sy"]] for c in tile["gcps"]])
            full, sums = renderer.render_markers(geometry, view, pts, slopes, cfg["marker_px"] * gsd,
                                                 cfg["depth_bias"],
                                                 marker_depth_tolerance(persp, gsd, cfg["max_float_px"]))
            seen = observations(tile["gcps"], full, sums, (extent.xmin, extent.ymax), pixel)
    return rgba, seen


def shadow_view(pl: dict, tile: dict):
    """The tile's :class:`~pipeline25d.render.ShadowView` from its plan, or None without shadows."""
    from .render import ShadowView
    from .sun import Sun, SunFrame

    s = pl.get("shadows")
    if not s:
        return None
    frame = SunFrame(Sun(s["azimuth"], s["elevation"]), s["texel"])
    return ShadowView(frame, tuple(tile["shadow"]["window"]), tuple(tile["shadow"]["depth"]), s["ambient"],
                      s["bias"], s["radius"])


def _write_tile(pl: dict, tile: dict, rgba: np.ndarray, seen: list[dict], tiles_dir: str | Path) -> None:
    """GCPs, GeoTIFF, then the spec hash that marks the tile complete (see :func:`render_block`)."""
    from .atomic import write_text
    from .crs import horizontal_wkt
    from .raster import write_rgba_geotiff

    files = tile_files(tiles_dir, tile["row"], tile["col"])
    files["spec"].unlink(missing_ok=True)
    # the paper camera's tiles lie on its image plane, which is no CRS: the warp georeferences them
    wkt = "" if plan_camera(pl) == "paper" else horizontal_wkt(pl["crs"])
    write_csv(files["gcps"], seen, OBSERVATION_FIELDS)
    write_rgba_geotiff(files["tif"], rgba, extent_geotransform(pl, tile_content(pl, tile)[0]), wkt)
    write_text(files["spec"], tile["spec_hash"] + "\n")


def marker_depth_tolerance(p: Perspective, gsd: float, max_float_px: float) -> float:
    """View-depth gap (m) between a marker and the surface under it that shifts its image by max_float_px.

    A marker δ metres above the ground appears δ·cot φ from that ground on the map and
    δ / sin φ nearer in depth: the tolerance is max_float_px·gsd / cos φ (unbounded at nadir).
    """
    if p.elevation == 90:
        return math.inf
    return max_float_px * gsd / math.cos(math.radians(p.elevation))


# -- gcps, mosaic, warp, tms ---------------------------------------------------------------------
def gather_gcps(tile_csvs: list[str], out_csv: str | Path) -> list[dict]:
    rows = [r for p in tile_csvs for r in read_csv(p)]
    rows.sort(key=lambda r: r["id"])
    write_csv(out_csv, rows, OBSERVATION_FIELDS)
    return rows


def mosaic(tiles: list[str], out_vrt: str | Path) -> None:
    from .warp import build_mosaic

    build_mosaic(sorted(tiles), out_vrt)


def warp(mosaic_vrt: str | Path, gcps_csv: str | Path, plan_path: str | Path, warp_cfg: dict,
         out_cog: str | Path, out_json: str | Path, maps_cfg: dict | None = None,
         work_dir: str | Path | None = None) -> dict:
    """Choose the warp by cross-validation on the GCPs, write the COG, and record the check-point
    scores. ``work_dir`` keeps the warped map for the next run to patch."""
    from .map_parts import tile_parts
    from .warp import choose, raster_geotransform, warp_to_cog

    pl = read_plan(plan_path)
    obs = read_csv(gcps_csv)
    gt = raster_geotransform(mosaic_vrt)
    choice = choose(obs, pl, gt, warp_cfg["method"], warp_cfg["order"])
    parts = tile_parts((t["row"], t["col"]) for t in pl["tiles"])
    bounds = warp_to_cog(mosaic_vrt, obs, choice, pl, out_cog, parts=parts, work_dir=work_dir, **(maps_cfg or {}))   # compression, quality
    record = {"perspective": pl["perspective"], **choice, "n_observed": len(obs), "parts": bounds,
              "paper_method": paper_method_on(obs, pl, gt) if pl.get("projection") == "terrain" else None}
    write_json(out_json, record)
    log.info("%s: warp %s (order %s), check-point RMSD %s m", pl["perspective"]["id"], choice["method"],
             choice["order"], None if choice["rmsd_m"] is None else round(choice["rmsd_m"], 3))
    return record


def paper_method_on(obs: list[dict], plan: dict, gt: tuple[float, ...]) -> dict | None:
    """Check-point error of the paper's method (plane at z0 + polynomial warp) on the same GCPs.

    Each observed (terrain-relative) marker position is moved to where the plane projection
    puts it, by (DTM − z0)·cot φ·d: exact where the DTM is planar across the marker, since
    the render displaced the marker by its height above that DTM. So only the method differs,
    not the points nor their sampling noise. (The paper camera's image is an affine function
    of the plane projection, so its polynomial warp scores the same; ``projection: paper``
    renders it.)
    """
    from .camera import horizontal_direction, relief_factor
    from .warp import MIN_GCPS, residuals

    p = Perspective.from_id(plan["perspective"]["id"])
    if not obs or p.elevation == 90:   # at nadir both methods are the same orthophoto
        return None
    shift = horizontal_direction(p) * relief_factor(p)
    planar = [{**r, "map_x": r["map_x"] + (r["ground"] - plan["z0"]) * shift[0],
               "map_y": r["map_y"] + (r["ground"] - plan["z0"]) * shift[1]} for r in obs]
    n_gcp = sum(r["role"] == "gcp" for r in obs)
    orders = [k for k in (3, 2, 1) if n_gcp >= MIN_GCPS[k]]
    if not orders:
        return {"order": None, "rmsd_m": None, "rmsd_px": None, "max_m": None,
                "check_note": f"n/a ({n_gcp} GCPs)"}
    return residuals("polynomial", orders[0], planar, gt, plan["gsd"])
