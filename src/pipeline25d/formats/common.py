"""What every reader shares: its return type, reading a text file with clear errors, reprojection."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..crs import check_within_area_of_use, parse_crs, transform_points
from ..errors import InputFileError
from ..mesh import Mesh, MeshPart

AREA_SAMPLE = 2000   # vertices checked against the scene CRS's area of use


class Detail(NamedTuple):
    """How much detail the maps need, for readers of multi-resolution formats (3D Tiles, OSGB):
    ``max_error`` the largest geometric error (m) a drawn level may have, ``gsd`` the map's
    metres per pixel; None = full detail / unknown."""

    max_error: float | None = None
    gsd: float | None = None


class Loaded(NamedTuple):
    """What every reader returns (see :mod:`pipeline25d.formats`): the model's parts, float64,
    in the CRS named by ``crs``; None when the file does not say (the input's ``crs`` key,
    else the scene CRS, then applies)."""

    parts: list[MeshPart]
    crs: str | None


def read_text(path: Path, what: str) -> str:
    """The file's text (UTF-8, BOM tolerated); InputFileError naming ``what`` when unreadable."""
    try:
        return path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputFileError(path, f"{what} is missing") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(path, f"cannot read {what}: {exc}") from None


#: German AdV CRS names (urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH, in most German CityGML):
#: horizontal and height parts, EPSG codes
_ADV = {"ETRS89_UTM31": 25831, "ETRS89_UTM32": 25832, "ETRS89_UTM33": 25833, "ETRS89_GK3": 4647,
        "DE_DHHN2016_NH": 7837, "DE_DHHN92_NH": 5783, "DE_DHHN12_NH": 7699}


def crs_name(ref: str) -> str:
    """'AUTH:CODE' (compound: 'EPSG:h+v') of a CRS reference: an OGC URL
    (``http://www.opengis.net/def/crs/EPSG/0/6697``), URN (``urn:ogc:def:crs:EPSG::25832``,
    compound ``urn:ogc:def:crs,crs:EPSG::25832,crs:EPSG::5783``), an EPSG XML link
    (``http://www.opengis.net/gml/srs/epsg.xml#25832``) or an AdV name; other text unchanged."""
    ref = ref.strip()
    low = ref.lower()
    if "/def/crs/" in low:  # https://www.opengis.net/def/crs/EPSG/0/7415
        bits = ref.rstrip("/").split("/")
        return f"{bits[-3]}:{bits[-1]}"
    if low.startswith("urn:ogc:def:crs,"):  # compound: one URN per part
        codes = [crs_name("urn:ogc:def:" + part) for part in ref.split(",")[1:]]
        return codes[0] + "".join("+" + c.split(":")[-1] for c in codes[1:])
    if low.startswith("urn:ogc:def:crs:"):  # urn:ogc:def:crs:EPSG::7415
        bits = ref.split(":")
        return f"{bits[4]}:{bits[-1]}"
    if "epsg.xml#" in low:
        return "EPSG:" + ref.rsplit("#", 1)[1]
    if low.startswith("urn:adv:crs:"):
        codes = [_ADV.get(part) for part in ref[len("urn:adv:crs:"):].split("*")]
        if all(codes):
            return "EPSG:" + "+".join(str(c) for c in codes)
    return ref


def reproject_parts(parts: list[MeshPart], src_crs: str, scene_crs: str, where: str | Path) -> list[MeshPart]:
    """Parts moved from ``src_crs`` to ``scene_crs`` in one transform call.

    First checks that a sample of the vertices (converted to lon/lat) lies in the scene
    CRS's area of use, so a model in the wrong place fails with a CRSError naming
    ``where`` instead of yielding silently distorted coordinates.
    """
    if not parts or parse_crs(src_crs) == parse_crs(scene_crs):
        return parts
    allv = np.concatenate([p.vertices for p in parts])
    lonlat = transform_points(allv[:: max(1, len(allv) // AREA_SAMPLE)], src_crs, "EPSG:4979")
    check_within_area_of_use(lonlat, scene_crs, where=str(where))
    moved = transform_points(allv, src_crs, scene_crs)
    out, start = [], 0
    for p in parts:
        end = start + len(p.vertices)
        out.append(MeshPart(moved[start:end], p.faces, p.colors, p.uv, p.texture, p.name))
        start = end
    return out


def in_scene(loaded: Loaded, scene_crs: str, where: str | Path) -> Mesh:
    """A reader's result as a Mesh in ``scene_crs`` (``loaded.crs`` None: already there)."""
    parts = loaded.parts if loaded.crs is None else reproject_parts(loaded.parts, loaded.crs, scene_crs, where)
    return Mesh(parts, source=str(where))
