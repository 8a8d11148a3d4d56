"""Helpers every reader shares: reading a text file with clear errors, and reprojection."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..crs import check_within_area_of_use, parse_crs, transform_points
from ..errors import InputFileError
from ..mesh import MeshPart

AREA_SAMPLE = 2000   # vertices checked against the scene CRS's area of use


def read_text(path: Path, what: str) -> str:
    """The file's text (UTF-8, BOM tolerated); InputFileError naming ``what`` when unreadable."""
    try:
        return path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputFileError(path, f"{what} is missing") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(path, f"cannot read {what}: {exc}") from None


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
