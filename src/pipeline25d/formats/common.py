"""What every reader shares: its return type, reading a text file with clear errors, reprojection."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..crs import check_within_area_of_use, parse_crs, transform_points
from ..errors import InputFileError, UnsupportedFeatureError
from ..mesh import Mesh, MeshPart

AREA_SAMPLE = 2000   # vertices checked against the scene CRS's area of use
CONVERTER_TIMEOUT_S = 600


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


def run_converter(args: list[str], cwd: Path, output: Path, what: Path, package: str,
                  env: dict[str, str] | None = None) -> None:
    """Run an external model converter (osgconv, assimp) in ``cwd`` without a display.

    UnsupportedFeatureError naming ``what`` when the program is not installed (``package``
    provides it), InputFileError naming ``what`` with the program's last words when it fails
    or writes no ``output`` (relative to ``cwd``).
    """
    if shutil.which(args[0]) is None:
        raise UnsupportedFeatureError(what, f"reading it needs {args[0]} (Debian package {package})")
    run_env = {k: v for k, v in os.environ.items() if k != "DISPLAY"} | (env or {})
    try:
        proc = subprocess.run(args, cwd=cwd, env=run_env, capture_output=True, text=True, errors="replace",
                              timeout=CONVERTER_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise InputFileError(what, f"{args[0]} took longer than {CONVERTER_TIMEOUT_S} s") from None
    if proc.returncode or not (cwd / output).is_file():
        tail = " ".join((proc.stdout + proc.stderr).split())[-300:]
        raise InputFileError(what, f"{args[0]} cannot read it (corrupt, or not that format): {tail}")


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
