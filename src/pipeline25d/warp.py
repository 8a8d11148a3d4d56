"""Orthorectification: choose a warp by check-point error, then gdalwarp the mosaic.

Ground in a map-aligned render is exact on the reference plane z0 and displaced by
(z - z0)·cot φ along the view direction elsewhere; the warp maps image positions of GCPs
to their true (x, y). Methods: ``none`` (the render's own geotransform), polynomial of
order 1-3, or thin-plate spline. Each is fitted on the GCPs only and scored on the
held-out check points with GDAL's own GCP transformer, the one gdalwarp uses.
"""

from __future__ import annotations

import logging
import math
import subprocess
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .errors import GdalToolError
from .raster import gdal

log = logging.getLogger(__name__)

MIN_GCPS = {1: 3, 2: 6, 3: 10, "tps": 3}   # gdal's minimum GCP counts per polynomial order


def to_pixels(rows: list[dict], gt: tuple[float, ...]) -> np.ndarray:
    """(n, 2) [pixel, line] in a north-up raster with geotransform ``gt`` of the rows' map_x/map_y."""
    mx = np.array([r["map_x"] for r in rows], dtype=np.float64)
    my = np.array([r["map_y"] for r in rows], dtype=np.float64)
    return np.column_stack([(mx - gt[0]) / gt[1], (my - gt[3]) / gt[5]])


def gdal_gcps(rows: list[dict], gt: tuple[float, ...]) -> list:
    """GDAL GCPs pairing each row's image position (in the raster with ``gt``) with its true x, y, z."""
    g = gdal()
    return [g.GCP(r["x"], r["y"], r["z"], float(p), float(q)) for r, (p, q) in zip(rows, to_pixels(rows, gt))]


def predict(method: str, order: int, train: list[dict], query: list[dict], gt: tuple[float, ...]) -> np.ndarray:
    """Scene (x, y) of the ``query`` rows' image positions under a warp fitted on ``train``."""
    if method == "none":
        return np.array([[r["map_x"], r["map_y"]] for r in query], dtype=np.float64).reshape(-1, 2)
    g = gdal()
    ds = g.GetDriverByName("MEM").Create("", 1, 1, 1)
    ds.SetGCPs(gdal_gcps(train, gt), "")
    options = ["METHOD=GCP_TPS"] if method == "tps" else ["METHOD=GCP_POLYNOMIAL", f"MAX_GCP_ORDER={order}"]
    tr = g.Transformer(ds, None, options)
    pts = np.column_stack([to_pixels(query, gt), np.zeros(len(query))]).tolist()
    out, ok = tr.TransformPoints(0, pts)
    out = np.array(out, dtype=np.float64)[:, :2]
    out[~np.asarray(ok, dtype=bool)] = np.nan
    return out


def residuals(method: str, order: int, obs: list[dict], gt: tuple[float, ...], gsd: float) -> dict:
    """Check-point error of a method fitted on the GCPs: RMSD and max, metres and pixels."""
    train = [r for r in obs if r["role"] == "gcp"]
    check = [r for r in obs if r["role"] == "check"]
    result = {"method": method, "order": order, "n_gcp": len(train), "n_check": len(check),
              "rmsd_m": None, "rmsd_px": None, "max_m": None}
    if not check:
        return result
    xy = predict(method, order, train, check, gt)
    err = np.hypot(xy[:, 0] - [r["x"] for r in check], xy[:, 1] - [r["y"] for r in check])
    rmsd = float(np.sqrt(np.nanmean(err ** 2)))
    return {**result, "rmsd_m": rmsd, "rmsd_px": rmsd / gsd, "max_m": float(np.nanmax(err))}


def max_relief_displacement_px(obs: list[dict], plan: dict) -> float:
    """Largest |z − z0|·cot φ over the observed GCPs, in pixels."""
    el = plan["perspective"]["elevation"]
    if el == 90 or not obs:
        return 0.0
    cot = 1.0 / math.tan(math.radians(el))
    return max(abs(r["z"] - plan["z0"]) for r in obs) * cot / plan["gsd"]


def choose(obs: list[dict], plan: dict, gt: tuple[float, ...], method: str, order: int) -> dict:
    """The warp to apply and the scores behind the choice.

    ``auto``: none where relief displacement stays under half a pixel, otherwise the
    candidate (none, polynomial 1-3, tps) with the lowest check-point RMSD.
    """
    n_gcp = sum(r["role"] == "gcp" for r in obs)
    baseline = residuals("none", 0, obs, gt, plan["gsd"])
    relief = max_relief_displacement_px(obs, plan)
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
    scored = [baseline] + [residuals(m, o, obs, gt, plan["gsd"]) for m, o in candidates]
    if method != "auto":
        best = scored[-1] if candidates else baseline
    else:
        best = min(scored, key=lambda s: math.inf if s["rmsd_m"] is None else s["rmsd_m"])
    return {**best, "relief_px": relief, "candidates": scored}


def run_tool(args: list[str]) -> None:
    """Run a GDAL command-line tool; GdalToolError with its stderr on failure."""
    log.info("%s", " ".join(args))
    proc = subprocess.run(args, capture_output=True, text=True)
    if proc.returncode != 0:
        raise GdalToolError(f"{args[0]} failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}")


def build_mosaic(tiles: list[str], out_vrt: str | Path) -> None:
    """gdalbuildvrt over the tile GeoTIFFs (they share one pixel grid)."""
    with atomic_path(out_vrt) as tmp:
        run_tool(["gdalbuildvrt", "-q", str(tmp), *tiles])


def warp_to_cog(mosaic: str | Path, obs: list[dict], choice: dict, plan: dict, out: str | Path) -> None:
    """Write the north-up COG: gdalwarp with the chosen GCP warp, or a plain copy for none."""
    from .crs import horizontal_wkt

    crs = horizontal_wkt(plan["crs"])
    cog = ["-of", "COG", "-co", "COMPRESS=DEFLATE", "-co", "OVERVIEWS=AUTO"]
    with atomic_path(out) as tmp:
        if choice["method"] == "none":
            run_tool(["gdal_translate", "-q", *cog, str(mosaic), str(tmp)])
            return
        train = [r for r in obs if r["role"] == "gcp"]
        gcps = gdal_gcps(train, raster_geotransform(mosaic))
        gcp_vrt = Path(tmp).with_suffix(".gcps.vrt")
        try:
            gdal().Translate(str(gcp_vrt), str(mosaic), format="VRT", GCPs=gcps, outputSRS=crs)
            method = ["-tps"] if choice["method"] == "tps" else ["-order", str(choice["order"])]
            gsd = str(plan["gsd"])
            run_tool(["gdalwarp", "-q", *method, "-r", "bilinear", "-t_srs", crs, "-tr", gsd, gsd, "-tap",
                      "-dstalpha", "-multi", "-wo", "NUM_THREADS=ALL_CPUS", *cog, str(gcp_vrt), str(tmp)])
        finally:
            gcp_vrt.unlink(missing_ok=True)


def raster_geotransform(path: str | Path) -> tuple[float, ...]:
    return tuple(gdal().Open(str(path)).GetGeoTransform())
