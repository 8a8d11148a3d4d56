"""The viewer's overlays on the ground: vector layers (streets, paths, POIs) given in the config
(``viewer.overlays``), each converted once to GeoJSON in WGS 84 beside the page
(viewer/overlays/<name>.geojson), which the page draws on every perspective.

Any layer OGR reads (GeoJSON, GeoPackage, Shapefile ...) is taken; its CRS is its own (a GeoJSON
without one is WGS 84, RFC 7946) unless the overlay names ``crs``. Heights (a "height" property or
a 3rd coordinate, metres above the map's ground) are kept: the page displaces such points by
h·cot φ along the view direction of each oblique map.
"""

from __future__ import annotations

import re
from pathlib import Path

from pipeline25d.core.atomic import atomic_path
from pipeline25d.core.errors import InputFileError
from pipeline25d.core.raster import gdal

PALETTE = ("#ff00ff", "#00e5ff", "#ffea00", "#ff6d00", "#76ff03")


def overlay_name(spec: dict) -> str:
    """The overlay's name (its ``name``, else its file's stem), reduced to a safe file name."""
    return re.sub(r"[^A-Za-z0-9_-]+", "_", spec.get("name") or Path(spec["path"]).stem) or "overlay"


def write_overlays(specs: list[dict], out_dir: str | Path) -> list[dict]:
    """Convert every overlay of ``specs`` (config ``viewer.overlays``) into ``out_dir``/<name>.geojson
    (WGS 84, 9 decimals: under a millimetre) and return what the page needs: name, url (relative to
    ``out_dir``'s parent) and colour."""
    out_dir = Path(out_dir)
    entries, seen = [], set()
    for k, spec in enumerate(specs):
        name = overlay_name(spec)
        while name in seen:
            name += "_"
        seen.add(name)
        src = Path(spec["path"])
        options = {"format": "GeoJSON", "dstSRS": "EPSG:4326", "skipFailures": False,
                   "layerCreationOptions": ["COORDINATE_PRECISION=9", "WRITE_NAME=NO"]}
        if spec.get("crs"):
            options["srcSRS"] = spec["crs"]
        with atomic_path(out_dir / f"{name}.geojson") as tmp:
            why = f"cannot be read as a vector layer (config key viewer.overlays.{k}.path)"
            try:
                ds = gdal().VectorTranslate(str(tmp), str(src), **options)   # GDAL raises (core.raster)
            except RuntimeError as exc:
                raise InputFileError(src, f"{why}: {exc}") from None
            if ds is None:
                raise InputFileError(src, why)
            del ds                                                            # closes the file
        entries.append({"name": name, "url": f"{out_dir.name}/{name}.geojson",
                        "color": spec.get("color") or PALETTE[k % len(PALETTE)]})
    return entries
