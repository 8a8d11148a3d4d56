"""The web viewer: a Leaflet page over the gdal2tiles pyramids with a perspective switch.

Leaflet is copied next to the page (from the npm package the Makefile installs into
build/), so the viewer works offline and from a plain static file server.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from .atomic import write_text
from .errors import Pipeline25dError

TEMPLATE = Path(__file__).with_name("viewer") / "index.html.in"


def leaflet_dist() -> Path:
    """Leaflet's dist folder: $PIPELINE25D_LEAFLET, else build/node_modules/leaflet/dist."""
    env = os.environ.get("PIPELINE25D_LEAFLET")
    candidates = [Path(env)] if env else []
    candidates.append(Path(__file__).resolve().parents[2] / "build" / "node_modules" / "leaflet" / "dist")
    for path in candidates:
        if (path / "leaflet.js").exists():
            return path
    raise Pipeline25dError("Leaflet not found: run `make deps` (npm install leaflet into build/) "
                           "or set PIPELINE25D_LEAFLET to a leaflet/dist folder")


def tile_extension(tms_dir: Path) -> str:
    """The pyramid's tile file extension (png or webp), from the tiles themselves."""
    for path in tms_dir.rglob("*"):
        if path.suffix in (".png", ".webp"):
            return path.suffix[1:]
    return "png"


def zoom_range(tms_dir: Path) -> tuple[int, int]:
    zooms = sorted(int(p.name) for p in tms_dir.iterdir() if p.is_dir() and p.name.isdigit())
    return zooms[0], zooms[-1]


def write_viewer(report_json: str | Path, out_html: str | Path) -> None:
    report = json.loads(Path(report_json).read_text())
    results = Path(report_json).resolve().parents[1]
    entries = []
    for p in report["perspectives"]:
        zmin, zmax = zoom_range(results / "tms" / p["id"])
        warp = p["warp"]["method"] + (f" {p['warp']['order']}" if p["warp"]["method"] == "polynomial" else "")
        entries.append({"id": p["id"], "azimuth": p["azimuth"], "elevation": p["elevation"],
                        "rmsd_m": p["rmsd_m"], "rmsd_px": p["rmsd_px"], "warp": warp,
                        "lonlat_bounds": p["lonlat_bounds"], "min_zoom": zmin, "max_zoom": zmax,
                        "ext": tile_extension(results / "tms" / p["id"])})
    out_html = Path(out_html)
    dest = out_html.parent / "leaflet"
    dest.mkdir(parents=True, exist_ok=True)
    src = leaflet_dist()
    for name in ("leaflet.js", "leaflet.css"):
        shutil.copyfile(src / name, dest / name)
    shutil.copytree(src / "images", dest / "images", dirs_exist_ok=True)
    html = TEMPLATE.read_text().replace("@SCENE@", report["scene"]).replace("@PERSPECTIVES@", json.dumps(entries))
    write_text(out_html, html)
