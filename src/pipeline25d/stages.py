"""One function per workflow stage: pure functions of their input files and parameters.

The Snakemake rules (workflow/rules/*.smk) call these through thin scripts or
``python -m pipeline25d``; tests call them directly.
"""

from __future__ import annotations

import json
import logging
import statistics
from pathlib import Path

import numpy as np

from .atomic import write_json
from .chunks import load_npz, pack_parts, save_npz, unpack_parts
from .gcps import (CANDIDATE_FIELDS, OBSERVATION_FIELDS, assign_roles, grid_candidates, observations,
                   read_csv, write_csv)
from .ingest import write_chunks
from .lod import build_levels
from .mesh import Mesh
from .perspectives import Perspective
from .plan import plan_perspective, plan_tile, read_plan, tile_extent, tile_geotransform

log = logging.getLogger(__name__)


# -- ingest / lod --------------------------------------------------------------------------
def ingest(spec: dict, district: str, scene_crs: str, chunk_size: float, max_geometric_error: float,
           index_path: str | Path) -> dict:
    """Read one district and write its chunks beside ``index_path``."""
    from .formats import load_district

    mesh = load_district(spec, scene_crs, max_geometric_error=max_geometric_error)
    log.info("%s: %d triangles from %s", district, mesh.n_triangles, spec["path"])
    index_path = Path(index_path)
    return write_chunks(mesh, district, chunk_size, index_path.parent, index_path)


def build_lod(chunk_path: str | Path, out_npz: str | Path, out_json: str | Path, max_error: float,
              max_levels: int) -> dict:
    """Write the LOD pyramid of one chunk (npz) and its metadata (json, written last)."""
    data = load_npz(chunk_path)
    origin = data["origin"]
    mesh = Mesh(unpack_parts(data, origin), source=str(chunk_path))
    levels = build_levels(mesh, max_error=max_error, max_levels=max_levels)
    arrays = {"origin": origin, "n_levels": np.array(len(levels))}
    for k, (parts, _) in enumerate(levels):
        arrays.update(pack_parts(parts, origin, prefix=f"L{k}_"))
    save_npz(out_npz, arrays)
    meta = {"chunk": Path(chunk_path).stem, "bounds": mesh.bounds().tolist(),
            "errors": [e for _, e in levels], "triangles": [sum(p.n_triangles for p in ps) for ps, _ in levels]}
    write_json(out_json, meta)
    return meta


def load_chunk_level(lod_npz: str | Path, level: int) -> tuple[np.ndarray, list]:
    data = load_npz(lod_npz)
    origin = data["origin"]
    level = min(level, int(data["n_levels"]) - 1)
    return origin, unpack_parts(data, origin, prefix=f"L{level}_")


# -- scene: reference plane and GCP candidates --------------------------------------------------
def scene_setup(lod_jsons: list[str], terrain: str, z0_cfg, gcp_cfg: dict, scene_crs: str,
                out_scene: str | Path, out_candidates: str | Path) -> dict:
    """Scene bounds, reference plane z0 and the GCP candidates (with check-point roles)."""
    metas = [json.loads(Path(p).read_text()) for p in lod_jsons]
    bounds = np.array([m["bounds"] for m in metas])
    lo, hi = bounds[:, 0].min(axis=0), bounds[:, 1].max(axis=0)
    floor = float(np.median(bounds[:, 0, 2]))
    height_fn = _terrain_function(terrain, scene_crs, z0_cfg, floor)
    if gcp_cfg["source"] == "auto":
        cands = grid_candidates((lo[0], lo[1], hi[0], hi[1]), gcp_cfg["spacing"], height_fn,
                                gcp_cfg["holdout"], gcp_cfg["seed"])
    else:
        rows = read_csv(gcp_cfg["source"])
        cands = assign_roles([{k: r[k] for k in ("id", "x", "y", "z")} for r in rows],
                             gcp_cfg["holdout"], gcp_cfg["seed"])
    z0 = float(z0_cfg) if z0_cfg != "auto" else (
        float(statistics.median(c["z"] for c in cands)) if cands else floor)
    scene = {"bounds": [lo.tolist(), hi.tolist()], "z0": z0, "terrain": terrain,
             "n_candidates": len(cands), "n_chunks": len(metas)}
    write_csv(out_candidates, cands, CANDIDATE_FIELDS)
    write_json(out_scene, scene)
    return scene


def _terrain_function(terrain: str, scene_crs: str, z0_cfg, floor: float):
    """height(x, y) from a DTM path, or a flat plane (z0, or the median chunk floor)."""
    if terrain not in ("auto", "flat"):
        from .raster import DTM

        return DTM(terrain, scene_crs).sample
    level = float(z0_cfg) if z0_cfg != "auto" else floor
    return lambda x, y: np.full(len(x), level)


# -- plan ---------------------------------------------------------------------------------
def plan(perspective_id: str, lod_jsons: list[str], scene_json: str | Path, candidates_csv: str | Path,
         gsd: float, tile_size: int, max_error_px: float, crs: str, render: dict, out_plan: str | Path) -> dict:
    """Plan one perspective (see :mod:`pipeline25d.plan`); ``render`` holds render + marker settings."""
    scene = json.loads(Path(scene_json).read_text())
    chunks = []
    for p in lod_jsons:
        meta = json.loads(Path(p).read_text())
        chunks.append({"id": meta["chunk"], "district": Path(p).parent.name, "bounds": meta["bounds"],
                       "errors": meta["errors"]})
    result = plan_perspective(Perspective.from_id(perspective_id), chunks, read_csv(candidates_csv),
                              scene["z0"], gsd, tile_size, max_error_px, crs, render)
    write_json(out_plan, result)
    log.info("%s: %d tiles to render, %d empty tiles skipped", perspective_id, len(result["tiles"]),
             result["n_tiles_skipped"])
    return result


# -- render -------------------------------------------------------------------------------
def render_tile(plan_path: str | Path, row: int, col: int, lod_dir: str | Path,
                out_tif: str | Path, out_gcps: str | Path) -> dict:
    """Render tile (row, col) of a plan: RGBA GeoTIFF plus the GCPs seen whole in it."""
    from .crs import horizontal_wkt
    from .raster import write_rgba_geotiff
    from .render import TileRenderer, TileView, create_context

    pl = read_plan(plan_path)
    tile = plan_tile(pl, row, col)
    persp = Perspective.from_id(pl["perspective"]["id"])
    t, gsd, cfg = pl["tile_size"], pl["gsd"], tile["render"]
    chunks = [load_chunk_level(Path(lod_dir) / c["district"] / f"{c['id']}.npz", c["lod"]) for c in tile["chunks"]]
    depth = tuple(tile["depth_range"])
    ctx = create_context()
    try:
        renderer = TileRenderer(ctx, ambient=cfg["ambient"], samples=cfg["samples"])
        rgba = renderer.render_color(chunks, TileView(persp, pl["z0"], tile_extent(pl, row, col), depth, (t, t)))
        seen = []
        if tile["gcps"]:
            margin = int(np.ceil(cfg["marker_px"])) + 2
            extent = tile_extent(pl, row, col, margin)
            view = TileView(persp, pl["z0"], extent, depth, (t + 2 * margin, t + 2 * margin))
            pts = np.array([[c["x"], c["y"], c["z"]] for c in tile["gcps"]])
            full, sums = renderer.render_markers(chunks, view, pts, cfg["marker_px"] * gsd, cfg["depth_bias"])
            seen = observations(tile["gcps"], full, sums, (extent.xmin, extent.ymax), gsd)
    finally:
        ctx.release()
    write_rgba_geotiff(out_tif, rgba, tile_geotransform(pl, row, col), horizontal_wkt(pl["crs"]))
    write_csv(out_gcps, seen, OBSERVATION_FIELDS)
    log.info("%s tile %d_%d: %d chunks, coverage %.1f%%, GCPs seen %d of %d", persp.id, row, col,
             len(chunks), 100 * float((rgba[..., 3] > 0).mean()), len(seen), len(tile["gcps"]))
    return {"gcps_candidates": len(tile["gcps"]), "gcps_seen": len(seen)}


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
         out_cog: str | Path, out_json: str | Path) -> dict:
    """Choose the warp by check-point error, write the COG, and record the scores."""
    from .warp import choose, raster_geotransform, warp_to_cog

    pl = read_plan(plan_path)
    obs = read_csv(gcps_csv)
    choice = choose(obs, pl, raster_geotransform(mosaic_vrt), warp_cfg["method"], warp_cfg["order"])
    warp_to_cog(mosaic_vrt, obs, choice, pl, out_cog)
    record = {"perspective": pl["perspective"], **choice,
              "n_observed": len(obs)}
    write_json(out_json, record)
    log.info("%s: warp %s (order %s), check-point RMSD %s m", pl["perspective"]["id"], choice["method"],
             choice["order"], None if choice["rmsd_m"] is None else round(choice["rmsd_m"], 3))
    return record


def tms(cog: str | Path, zoom: str, out_dir: str | Path, processes: int = 1) -> None:
    """gdal2tiles XYZ pyramid (web mercator) of a map, built in a temporary folder then moved."""
    import sys
    import tempfile

    from .atomic import replace_dir
    from .warp import run_tool

    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    try:
        args = [sys.executable, "-m", "osgeo_utils.gdal2tiles", "-q", "--xyz", "-w", "none", "-r", "average",
                f"--processes={processes}"]
        if zoom != "auto":
            args += ["-z", zoom]
        run_tool(args + [str(cog), str(tmp)])
        replace_dir(tmp, out_dir)
    except BaseException:
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)
        raise
