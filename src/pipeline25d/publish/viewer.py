"""The web viewer: a Leaflet page over the gdal2tiles pyramids with a perspective switch.

Leaflet, its rotation plugin (leaflet-rotate: the view direction turned up the screen) and the
PMTiles decoder are copied next to the page (from the npm packages the Makefile installs into
build/), and so are the viewer's own viewer.js and viewer.css, so the viewer works offline
and from a plain static file server. The page is given, per perspective, its azimuth,
elevation and gsd (for measuring heights), the runs of tiles its pyramid holds (so the
browser never asks for a tile that was not written: empty tiles are not cut) and, where the
pyramid was also written as one PMTiles archive, that archive's path; per scene, a quadratic
from web-mercator metres to the scene CRS (measurements are made there), the overlays (converted
beside the page by :mod:`pipeline25d.publish.overlays`) and the basemap, if any. With the id
layer (``ids``: the folder holding ``idtiles/<id>/`` and ``objects/shards/``, the results folder in a
run), each perspective also gets its id tiles' folder and runs, from which identify.js tells the
object under the pointer, its row read from the objects' shards.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np

from pipeline25d.core.atomic import write_text
from pipeline25d.core.errors import Pipeline25dError
from pipeline25d.core.node_modules import package_folder
from pipeline25d.publish.overlays import write_overlays
from pipeline25d.publish.report import warp_label
from pipeline25d.stages.tiles import ids as id_tiles

TEMPLATE = Path(__file__).with_name("viewer") / "index.html.in"


# npm package -> the files of its dist folder the page loads (copied to viewer/<package>/)
NODE_FILES = {"leaflet": ("leaflet.js", "leaflet.css", "images"), "leaflet-rotate": ("leaflet-rotate.js",),
              "pmtiles": ("pmtiles.js",)}


def node_dist(package: str) -> Path:
    """An npm package's dist folder (:func:`~pipeline25d.core.node_modules.package_folder`)."""
    return package_folder(package, "dist", NODE_FILES[package])


def tile_extension(tms_dir: Path) -> str:
    """The pyramid's tile file extension (png or webp), from the tiles themselves."""
    for path in tms_dir.rglob("*"):
        if path.suffix in (".png", ".webp"):
            return path.suffix[1:]
    return "png"


def zoom_range(tms_dir: Path) -> tuple[int, int]:
    zooms = sorted(int(p.name) for p in tms_dir.iterdir() if p.is_dir() and p.name.isdigit())
    return zooms[0], zooms[-1]


def tile_runs(tms_dir: Path, ext: str) -> dict[str, dict[str, list[list[int]]]]:
    """The pyramid's tiles as {z: {x: [[y0, y1], ...]}}, inclusive runs of consecutive y: a map's
    tiles per column are a few runs, so this stays small at city scale."""
    cols: dict[str, dict[str, list[int]]] = {}
    for path in tms_dir.glob(f"*/*/*.{ext}"):
        z, x = path.parent.parent.name, path.parent.name
        cols.setdefault(z, {}).setdefault(x, []).append(int(path.stem))
    runs: dict[str, dict[str, list[list[int]]]] = {}
    for z, xs in cols.items():
        for x, ys in xs.items():
            out: list[list[int]] = []
            for y in sorted(ys):
                if out and y == out[-1][1] + 1:
                    out[-1][1] = y
                else:
                    out.append([y, y])
            runs.setdefault(z, {})[x] = out
    return runs


def id_entry(id_dir: Path, rel) -> dict | None:
    """A perspective's id pyramid for the page: its folder (``rel``: as the page reaches it), tile runs
    and finest zoom (None: no id tiles)."""
    if not id_dir.is_dir() or not any(id_dir.rglob(f"*.{id_tiles.EXT}")):
        return None
    return {"url": rel(id_dir), "tiles": tile_runs(id_dir, id_tiles.EXT), "max_zoom": zoom_range(id_dir)[1],
            "ext": id_tiles.EXT}


def mercator_to_scene(crs: str, lonlat_bounds: list[float], n: int = 7) -> dict:
    """Quadratic least-squares fit of scene CRS (x, y) over web-mercator metres (X, Y) on an n × n grid
    over [west, south, east, north]: x = Σ coef·[1, u, v, u², uv, v²] with u, v = ((X, Y) − origin) / scale.
    Its worst error on the grid is ``max_error_m`` (well under a millimetre over a city)."""
    from pipeline25d.core.crs import transform_points

    w, s, e, n_ = lonlat_bounds
    lon, lat = np.meshgrid(np.linspace(w, e, n), np.linspace(s, n_, n))
    ll = np.column_stack([lon.ravel(), lat.ravel(), np.zeros(lon.size)])
    merc = transform_points(ll, "EPSG:4326", "EPSG:3857")[:, :2]
    scene = transform_points(ll, "EPSG:4326", crs)[:, :2]
    origin = merc.mean(axis=0)
    scale = float(np.abs(merc - origin).max()) or 1.0
    u, v = ((merc - origin) / scale).T
    terms = np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])
    coef = np.linalg.lstsq(terms, scene, rcond=None)[0]
    return {"origin": origin.tolist(), "scale": scale, "x": coef[:, 0].tolist(), "y": coef[:, 1].tolist(),
            "max_error_m": float(np.abs(terms @ coef - scene).max())}


def write_viewer(report_json: str | Path, out_html: str | Path, archives: list[str | Path] | None = None,
                 overlays: list[dict] | None = None, basemap: dict | None = None,
                 ids: str | Path | None = None) -> None:
    """Write the viewer page ``out_html`` with its scripts beside it. ``archives``: PMTiles archives
    named ``<id>.pmtiles``, one per perspective; the page then reads those instead of the XYZ folders.
    ``overlays`` (config ``viewer.overlays``): vector layers copied beside the page as GeoJSON and drawn
    on every perspective; ``basemap`` (config ``viewer.basemap``): an XYZ layer under the maps; ``ids``:
    the folder of the id layer (``idtiles/<id>/``, ``objects/shards/``): hovering and clicking then
    identify objects."""
    report = json.loads(Path(report_json).read_text())
    results = Path(report_json).resolve().parents[1]
    out_html = Path(out_html)

    def rel(path: Path) -> str:
        return Path(os.path.relpath(path.resolve(), out_html.parent.resolve())).as_posix()

    archive = {Path(a).stem: Path(os.path.relpath(Path(a).resolve(), out_html.parent.resolve())).as_posix()
               for a in archives or []}
    if archive and set(archive) != {p["id"] for p in report["perspectives"]}:
        raise Pipeline25dError(f"{report_json}: PMTiles archives {sorted(archive)} are not one per perspective")
    entries = []
    for p in report["perspectives"]:
        tms_dir = results / "tms" / p["id"]
        zmin, zmax = zoom_range(tms_dir)
        ext = tile_extension(tms_dir)
        warp = warp_label(p)
        entries.append({"id": p["id"], "azimuth": p["azimuth"], "elevation": p["elevation"], "gsd": report["gsd"],
                        "rmsd_m": p["rmsd_m"], "rmsd_px": p["rmsd_px"], "warp": warp,
                        "lonlat_bounds": p["lonlat_bounds"], "min_zoom": zmin, "max_zoom": zmax,
                        "ext": ext, "tiles": tile_runs(tms_dir, ext), "pmtiles": archive.get(p["id"]),
                        "ids": id_entry(Path(ids) / "idtiles" / p["id"], rel) if ids else None})
    bounds = np.array([p["lonlat_bounds"] for p in entries])
    to_scene = mercator_to_scene(report["crs"], [*bounds[:, :2].min(axis=0), *bounds[:, 2:].max(axis=0)])
    for package, names in NODE_FILES.items():
        src, dest = node_dist(package), out_html.parent / package
        dest.mkdir(parents=True, exist_ok=True)
        for name in names:
            if (src / name).is_dir():
                shutil.copytree(src / name, dest / name, dirs_exist_ok=True)
            else:
                shutil.copyfile(src / name, dest / name)
    for name in ("viewer.js", "overlays.js", "identify.js", "viewer.css"):
        shutil.copyfile(TEMPLATE.with_name(name), out_html.parent / name)
    html = (TEMPLATE.read_text().replace("@SCENE@", report["scene"]).replace("@PERSPECTIVES@", json.dumps(entries))
            .replace("@TO_SCENE@", json.dumps(to_scene))
            .replace("@OVERLAYS@", json.dumps(write_overlays(overlays or [], out_html.parent / "overlays")))
            .replace("@BASEMAP@", json.dumps(basemap))
            .replace("@OBJECTS@", json.dumps(rel(Path(ids) / "objects" / "shards") if ids else None)))
    write_text(out_html, html)
