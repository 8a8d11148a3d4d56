"""Orthorectification: choose a warp by cross-validation on the GCPs, then gdalwarp the mosaic.

In plane mode, ground in a map-aligned render is exact on the reference plane z0 and
displaced by (z − z0)·cot φ along the view direction elsewhere; in terrain mode by its
height above the DTM. The warp maps image positions of GCPs to their true (x, y).
Methods: ``none`` (the render's own geotransform), polynomial of order 1-3, or thin-plate
spline, all through GDAL's own GCP transformer (the one gdalwarp uses).

The choice uses the GCPs alone (k-fold cross-validation); the held-out check points are
scored only after it, so their RMSD is an honest estimate. Fewer than
:data:`MIN_CHECK_POINTS` check points give no figure ("n/a"), never 0.
"""

from __future__ import annotations

import logging
import math
import shutil
import subprocess
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import atomic_path, write_json
from pipeline25d.core.cores import job_workers
from pipeline25d.core.errors import GdalToolError
from pipeline25d.core.grid import Grid
from pipeline25d.core.raster import gdal, tool_env
from pipeline25d.stages.gcps import read_observations
from pipeline25d.stages.maps.patch import transformer_options
from pipeline25d.stages.plan import read_plan
from pipeline25d.stages.records import Observation, Plan

log = logging.getLogger(__name__)

MIN_GCPS = {1: 3, 2: 6, 3: 10, "tps": 3}   # gdal's minimum GCP counts per polynomial order
MIN_CHECK_POINTS = 5                       # fewer check points than this: the RMSD is reported as n/a
CV_FOLDS = 5
CV_MAX_GCPS = 600                          # cross-validation subsamples larger GCP sets (TPS is cubic in n)
WARP_GAIN, WARP_MIN_GAIN_PX = 1.1, 0.1     # auto warps only where none's CV error exceeds 1.1 × best + 0.1 px


def to_pixels(rows: Sequence[Observation], grid: Grid) -> np.ndarray:
    """(n, 2) [pixel, line] on the raster ``grid`` of the rows' map_x/map_y."""
    mx = np.array([r.map_x for r in rows], dtype=np.float64)
    my = np.array([r.map_y for r in rows], dtype=np.float64)
    return np.column_stack(grid.colrow(mx, my))


def gdal_gcps(rows: Sequence[Observation], grid: Grid) -> list:
    """GDAL GCPs pairing each row's image position (on the raster ``grid``) with its true x, y, z."""
    g = gdal()
    return [g.GCP(r.x, r.y, r.z, float(p), float(q)) for r, (p, q) in zip(rows, to_pixels(rows, grid))]


def predict(method: str, order: int, train: Sequence[Observation], query: Sequence[Observation],
            grid: Grid) -> np.ndarray:
    """Scene (x, y) of the ``query`` rows' image positions under a warp fitted on ``train``."""
    if method == "none":
        return np.array([[r.map_x, r.map_y] for r in query], dtype=np.float64).reshape(-1, 2)
    g = gdal()
    ds = g.GetDriverByName("MEM").Create("", 1, 1, 1)
    ds.SetGCPs(gdal_gcps(train, grid), "")
    tr = g.Transformer(ds, None, transformer_options(method, order))
    pts = np.column_stack([to_pixels(query, grid), np.zeros(len(query))]).tolist()
    out, ok = tr.TransformPoints(0, pts)
    out = np.array(out, dtype=np.float64)[:, :2]
    out[~np.asarray(ok, dtype=bool)] = np.nan
    return out




def _errors(method: str, order: int, train: Sequence[Observation], query: Sequence[Observation],
            grid: Grid) -> np.ndarray:
    """(n,) metres between the query rows' predicted and true (x, y)."""
    xy = predict(method, order, train, query, grid)
    return np.hypot(xy[:, 0] - [r.x for r in query], xy[:, 1] - [r.y for r in query])


def residuals(method: str, order: int, obs: Sequence[Observation], grid: Grid, gsd: float) -> dict:
    """Check-point error of a method fitted on the GCPs: RMSD and max, metres and pixels.

    With fewer than MIN_CHECK_POINTS check points the figures are None and ``check_note``
    says how many there were.
    """
    train = [r for r in obs if r.role == "gcp"]
    check = [r for r in obs if r.role == "check"]
    result = {"method": method, "order": order, "n_gcp": len(train), "n_check": len(check),
              "rmsd_m": None, "rmsd_px": None, "max_m": None, "check_note": f"n/a ({len(check)} check points)"}
    if len(check) < MIN_CHECK_POINTS:
        return result
    err = _errors(method, order, train, check, grid)
    rmsd = float(np.sqrt(np.nanmean(err ** 2)))
    return {**result, "rmsd_m": rmsd, "rmsd_px": rmsd / gsd, "max_m": float(np.nanmax(err)),
            "check_note": f"{len(check)} check points"}


def cross_validated_rmsd(method: str, order: int, gcps: Sequence[Observation], grid: Grid,
                         folds: int = CV_FOLDS, seed: int = 0) -> float | None:
    """k-fold cross-validated RMSD (m) of a method on the GCPs alone; None where a fold cannot be fitted."""
    if method == "none":
        return float(np.sqrt(np.mean(_errors("none", 0, [], gcps, grid) ** 2))) if gcps else None
    rng = np.random.default_rng(seed)
    rows = [gcps[i] for i in rng.permutation(len(gcps))[:CV_MAX_GCPS]]
    need = MIN_GCPS["tps" if method == "tps" else order]
    fold = np.arange(len(rows)) % folds
    errs = []
    for k in range(folds):
        train = [r for r, f in zip(rows, fold) if f != k]
        test = [r for r, f in zip(rows, fold) if f == k]
        if len(train) < need:
            return None
        if test:
            errs.append(_errors(method, order, train, test, grid))
    err = np.concatenate(errs) if errs else np.array([np.nan])
    return float(np.sqrt(np.nanmean(err ** 2))) if np.isfinite(err).any() else None


def max_relief_displacement_px(obs: Sequence[Observation], plan: Plan) -> float:
    """Largest |height above the reference|·cot φ over the observed GCPs, in pixels.

    The reference is the DTM under each GCP in terrain mode, the plane z0 in plane mode.
    """
    el = plan.perspective.elevation
    if el == 90 or not obs:
        return 0.0
    cot = 1.0 / math.tan(math.radians(el))
    relative = plan.projection == "terrain"
    return max(abs(r.z - (r.ground if relative else plan.z0)) for r in obs) * cot / plan.gsd


def choose(obs: Sequence[Observation], plan: Plan, grid: Grid, method: str, order: int) -> dict:
    """The warp to apply and the scores behind the choice.

    ``auto``: none where relief displacement stays under half a pixel, otherwise the
    candidate (none, polynomial 1-3, tps) with the lowest cross-validated RMSD on the
    GCPs. Check-point figures of every candidate are recorded, but none enters the choice.
    The paper camera's image is not a map: there, ``auto`` and ``none`` mean the paper's
    polynomial warp, and the unwarped "none" is scored as n/a.
    """
    gcps = [r for r in obs if r.role == "gcp"]
    n_gcp = len(gcps)
    relief = max_relief_displacement_px(obs, plan)
    if plan.projection == "paper":
        baseline = {**residuals("none", 0, [], grid, plan.gsd), "cv_rmsd_m": None,
                    "check_note": "n/a (the paper camera's image is not a map)"}
        method = "polynomial" if method in ("auto", "none") else method
    else:
        baseline = {**residuals("none", 0, obs, grid, plan.gsd),
                    "cv_rmsd_m": cross_validated_rmsd("none", 0, gcps, grid)}
    if method == "none" or (method == "auto" and relief < 0.5):
        return {**baseline, "relief_px": relief, "candidates": [baseline]}
    if method == "polynomial":
        # the configured order, or the highest lower one the GCP count supports
        usable = [k for k in range(order, 0, -1) if n_gcp >= MIN_GCPS[k]]
        candidates = [("polynomial", usable[0])] if usable else []
    elif method == "tps":
        candidates = [("tps", 0)] if n_gcp >= MIN_GCPS["tps"] else []
    else:
        candidates = [("polynomial", k) for k in (1, 2, 3) if n_gcp >= MIN_GCPS[k]]
        candidates += [("tps", 0)] if n_gcp >= MIN_GCPS["tps"] else []
    # Cross-validation (on subsamples) for every candidate; the full fit that scores check
    # points is cubic in the GCP count for TPS, so a large TPS is scored only if it is chosen.
    scored = [baseline] + [{"method": m, "order": o, "cv_rmsd_m": cross_validated_rmsd(m, o, gcps, grid)}
                           for m, o in candidates]
    if method != "auto":
        if not candidates and plan.projection == "paper":
            raise ValueError(f"{plan.id}: {n_gcp} GCPs observed, too few for the paper's "
                             f"{method} warp (order 1 needs {MIN_GCPS[1]})")
        best = scored[-1] if candidates else baseline
    else:
        best = min(scored, key=lambda s: math.inf if s["cv_rmsd_m"] is None else s["cv_rmsd_m"])
        # A warp resamples the whole map: take one only where it clearly beats none.
        if baseline["cv_rmsd_m"] is not None and best["cv_rmsd_m"] is not None and \
                baseline["cv_rmsd_m"] <= WARP_GAIN * best["cv_rmsd_m"] + WARP_MIN_GAIN_PX * plan.gsd:
            best = baseline
    for i, cand in enumerate(scored[1:], 1):
        if cand is best or cand["method"] != "tps" or n_gcp <= CV_MAX_GCPS:
            scored[i] = {**residuals(cand["method"], cand["order"], obs, grid, plan.gsd), **cand}
        else:
            scored[i] = {**residuals(cand["method"], cand["order"], [], grid, plan.gsd), **cand, "n_gcp": n_gcp,
                         "check_note": f"not scored (TPS on {n_gcp} GCPs, not chosen)"}
        if cand is best:
            best = scored[i]
    return {**best, "relief_px": relief, "candidates": scored}


def run_tool(args: list[str]) -> None:
    """Run a GDAL command-line tool; GdalToolError with its stderr on failure."""
    log.info("%s", " ".join(args))
    proc = subprocess.run(args, capture_output=True, text=True, env=tool_env())
    if proc.returncode != 0:
        raise GdalToolError(f"{args[0]} failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}")


def gcp_source(mosaic: str | Path, obs: Sequence[Observation], crs: str, out_vrt: str | Path) -> Path:
    """A VRT of ``mosaic`` carrying the GCPs (role gcp) of ``obs`` in ``crs``: what a GCP warp reads."""
    train = [r for r in obs if r.role == "gcp"]
    gdal().Translate(str(out_vrt), str(mosaic), format="VRT", GCPs=gdal_gcps(train, raster_grid(mosaic)), outputSRS=crs)
    return Path(out_vrt)


def cog_codec(compression: str, quality: int) -> list[str]:
    """The COG driver's creation options for ``compression`` (deflate, jpeg or webp) at ``quality``."""
    # DEFLATE level 1 after horizontal differencing: smaller than level 6 alone and ~25 % faster
    if compression == "deflate":
        return ["COMPRESS=DEFLATE", "PREDICTOR=2", "LEVEL=1"]
    return [f"COMPRESS={compression.upper()}", f"QUALITY={int(quality)}"]


def cog_options(compression: str, quality: int) -> list[str]:
    """The COG driver's options for a map copied from a raster with its overviews built: its codec,
    those overviews kept (jpeg: the alpha becomes a mask, whose overviews the COG driver must
    make, averaging over the whole map), and its empty blocks unstored (SPARSE_OK: read as the
    zeros they hold; Zurich's 368 Mpx map: 2.9 s instead of 10.3 s, 0.36 MB instead of 2.5 MB)."""
    overviews = ["OVERVIEWS=AUTO", "RESAMPLING=AVERAGE"] if compression == "jpeg" else ["OVERVIEWS=FORCE_USE_EXISTING"]
    return [*cog_codec(compression, quality), *overviews, "SPARSE_OK=TRUE"]


def encode_options(options: list[str], threads: int) -> list[str]:
    """The COG driver's ``options`` and the threads it compresses blocks with: the job's ``threads``,
    or the cores idle at this moment where more (:func:`~pipeline25d.core.cores.job_workers`), so
    a map encoded while the other jobs have ended takes their cores (same bytes)."""
    return [*options, f"NUM_THREADS={job_workers(threads)}"]


def warp_to_cog(mosaic: str | Path, obs: Sequence[Observation], choice: dict, plan: Plan, out: str | Path,
                compression: str = "deflate", quality: int = 85,
                parts: list[tuple[int, int, int, int]] | None = None,
                work_dir: str | Path | None = None, threads: int = 1,
                cells_memo: dict | None = None, cells_note: str | Path | None = None) -> list[list[float]]:
    """Write the north-up COG: the mosaic warped with the chosen GCP warp, or a plain copy for none.

    ``compression``: deflate (lossless RGBA), jpeg (RGB + the alpha as a mask, which the COG
    driver makes) or webp (RGBA), the last two at ``quality``. ``parts``: the tile rectangles of
    :func:`pipeline25d.stages.maps.parts.tile_parts`; more than one makes a sparse map, warped part by
    part (see :mod:`pipeline25d.stages.maps.parts`). Returns each part's bounds [xmin, ymin, xmax, ymax]
    on the map (one part: the whole map's). A dense map is kept in ``work_dir`` with its
    overviews and patched where the mosaic changed (:mod:`pipeline25d.stages.maps.patch`).
    ``threads``: the job's threads, with which GDAL compresses the COG's blocks, or the cores idle
    when it does where more (:func:`encode_options`; same bytes). ``cells_note``: where a dense,
    lossless map's digests (taken as its blocks were made) are kept for its web tiles
    (:func:`pipeline25d.core.raster.write_cells_note`).
    """
    from pipeline25d.core.crs import horizontal_wkt
    from pipeline25d.core.raster import write_cells_note

    crs = horizontal_wkt(plan.crs)
    codec = cog_options(compression, quality)
    if cells_note:
        Path(cells_note).unlink(missing_ok=True)
    with atomic_path(out) as tmp:
        gcp_vrt = Path(tmp).with_suffix(".gcps.vrt")
        try:
            source = Path(mosaic)
            if choice["method"] != "none":
                source = gcp_source(mosaic, obs, crs, gcp_vrt)
            if parts and len(parts) > 1:
                return _warp_parts(source, mosaic, choice, plan, crs, parts, tmp, codec, threads)
            from pipeline25d.stages.maps.patch import patched_map

            kept_dir = Path(work_dir) if work_dir else Path(tmp).with_suffix(".blocks")
            try:
                kept, stats = patched_map(mosaic, source, choice, crs, plan.gsd, kept_dir, cells_memo, threads)
                cog = [opt for c in encode_options(codec, threads) for opt in ("-co", c)]
                run_tool(["gdal_translate", "-q", "-of", "COG", *cog, str(kept), str(tmp)])
            finally:
                if not work_dir:
                    shutil.rmtree(kept_dir, ignore_errors=True)
            bounds = [list(Grid.of_dataset(gdal().Open(str(tmp))).bounds)]
        finally:
            gcp_vrt.unlink(missing_ok=True)
    if cells_note and compression == "deflate" and stats["map_cells"] is not None:    # the COG holds the same pixels
        write_cells_note(cells_note, out, *stats["map_cells"])
    return bounds


def _warp_parts(source: Path, mosaic: str | Path, choice: dict, plan: Plan, crs: str,
                parts: list[tuple[int, int, int, int]], out: Path, codec: list[str],
                threads: int) -> list[list[float]]:
    """A sparse COG: each part warped onto the map grid with its overviews, then assembled
    (``codec``: the COG driver's options, :func:`cog_options`, encoded by :func:`encode_options`)."""
    from pipeline25d.stages.maps.parts import (
        assemble_sparse_cog,
        map_grid,
        overview_factors,
        part_bounds,
    )
    from pipeline25d.stages.maps.patch import source_to_map, window_warp_options

    g = gdal()
    mosaic_grid = raster_grid(mosaic)
    if choice["method"] == "none":
        def to_map(x, y):
            return x, y
    else:
        pixels_to_map = source_to_map(source, choice)

        def to_map(x, y):
            return pixels_to_map(*mosaic_grid.colrow(x, y))

    gsd = plan.gsd
    grid, windows = map_grid(part_bounds(plan, parts, to_map), gsd)
    width, height = grid.width, grid.height
    factors = overview_factors(width, height)
    warp_options = {**window_warp_options(choice, crs, gsd), "format": "GTiff",
                    "creationOptions": ["TILED=YES", "COMPRESS=ZSTD", "ZSTD_LEVEL=1"]}
    part_files = []
    try:
        for k, win in enumerate(windows):
            path = out.with_suffix(f".part{k}.tif")
            part_files.append((path, win))
            g.Warp(str(path), str(source), outputBounds=grid.window_bounds(win), **warp_options)
            ds = g.Open(str(path), 1)
            if factors:
                # a file opened for update compresses its overviews at zstd's default level (9) unless told
                g.SetConfigOption("ZSTD_LEVEL_OVERVIEW", "1")
                try:
                    ds.BuildOverviews("AVERAGE", factors)
                finally:
                    g.SetConfigOption("ZSTD_LEVEL_OVERVIEW", None)
            ds = None
        log.info("sparse map: %d parts, %d x %d px, %.1f%% of it in parts", len(windows), width, height,
                 100 * sum(w.width * w.height for w in windows) / (width * height))
        assemble_sparse_cog(part_files, grid, crs, out, encode_options(codec, threads))
    finally:
        for path, _ in part_files:
            path.unlink(missing_ok=True)
            Path(str(path) + ".ovr").unlink(missing_ok=True)
    return [list(grid.window_bounds(w)) for w in windows]


def raster_grid(path: str | Path) -> Grid:
    return Grid.of_dataset(gdal().Open(str(path)))


def warp(mosaic_vrt: str | Path, gcps_csv: str | Path, plan_path: str | Path, warp_cfg: dict,
         out_cog: str | Path, out_json: str | Path, maps_cfg: dict | None = None,
         work_dir: str | Path | None = None, threads: int = 1, cells_memo: dict | None = None,
         cells_note: str | Path | None = None) -> dict:
    """Choose the warp by cross-validation on the GCPs, write the COG, and record the check-point
    scores. ``work_dir`` keeps the warped map for the next run to patch; ``threads`` encode the COG;
    ``cells_memo``: the job's mosaic digests (:func:`pipeline25d.core.raster.map_cells`), kept for its id map;
    ``cells_note``: where the map's own digests are kept for its web tiles (:func:`warp_to_cog`)."""
    from pipeline25d.stages.maps.parts import tile_parts

    pl = read_plan(plan_path)
    obs = read_observations(gcps_csv)
    grid = raster_grid(mosaic_vrt)
    choice = choose(obs, pl, grid, warp_cfg["method"], warp_cfg["order"])
    parts = tile_parts((t.row, t.col) for t in pl.tiles)
    bounds = warp_to_cog(mosaic_vrt, obs, choice, pl, out_cog, parts=parts, work_dir=work_dir, threads=threads,
                         cells_memo=cells_memo, cells_note=cells_note, **(maps_cfg or {}))   # compression, quality
    p = pl.perspective
    record = {"perspective": {"id": p.id, "azimuth": p.azimuth, "elevation": p.elevation}, **choice,
              "n_observed": len(obs), "parts": bounds,
              "paper_method": paper_method_on(obs, pl, grid) if pl.projection == "terrain" else None}
    write_json(out_json, record)
    log.info("%s: warp %s (order %s), check-point RMSD %s m", pl.id, choice["method"],
             choice["order"], None if choice["rmsd_m"] is None else round(choice["rmsd_m"], 3))
    return record


def paper_method_on(obs: Sequence[Observation], plan: Plan, grid: Grid) -> dict | None:
    """Check-point error of the paper's method (plane at z0 + polynomial warp) on the same GCPs.

    Each observed (terrain-relative) marker position is moved to where the plane projection
    puts it, by (DTM − z0)·cot φ·d: exact where the DTM is planar across the marker, since
    the render displaced the marker by its height above that DTM. So only the method differs,
    not the points nor their sampling noise. (The paper camera's image is an affine function
    of the plane projection, so its polynomial warp scores the same; ``projection: paper``
    renders it.)
    """
    from pipeline25d.geometry.camera import horizontal_direction, relief_factor

    p = plan.perspective
    if not obs or p.elevation == 90:   # at nadir both methods are the same orthophoto
        return None
    shift = horizontal_direction(p) * relief_factor(p)
    planar = [replace(r, map_x=r.map_x + (r.ground - plan.z0) * shift[0],
                      map_y=r.map_y + (r.ground - plan.z0) * shift[1]) for r in obs]
    n_gcp = sum(r.role == "gcp" for r in obs)
    orders = [k for k in (3, 2, 1) if n_gcp >= MIN_GCPS[k]]
    if not orders:
        return {"order": None, "rmsd_m": None, "rmsd_px": None, "max_m": None,
                "check_note": f"n/a ({n_gcp} GCPs)"}
    return residuals("polynomial", orders[0], planar, grid, plan.gsd)
