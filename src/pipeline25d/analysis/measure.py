"""Measuring on one 2.5D map: heights of vertical edges, ground lengths and facade areas.

On a north-up oblique map (azimuth θ, elevation φ) a point h metres above the ground under it
appears at its ground position + h·c·d, with c = cot φ and d = (sin θ, cos θ) (DESIGN.md,
:mod:`pipeline25d.geometry.camera`). So:

* **height** of a vertical edge from its base B and top T on the map: the edge's image is
  T − B = h·c·d, hence h = (T − B)·d / c. The component of T − B across d, (T − B) × d, is
  how far the click pair is off the view direction (0 for a perfect pair). A click error of
  one pixel (gsd metres) along d changes h by gsd / c. On a nadir map (φ = 90°, c = 0) a
  vertical edge has no length and heights cannot be measured.
* **ground length**: ground points lie at their orthographic positions (terrain-relative
  maps, or ground at the plane z0), so it is the plain length of the polyline.
* **facade area** from a polygon P of map points on one planar vertical facade. Let e be the
  facade's horizontal unit direction and (s, z) a facade point's coordinates (s metres along
  e, z metres above the ground). It appears at B0 + s·e + z·c·d: in the frame (w, u) of the
  map, w across d and u along d, that is w = s·(e × d), u = s·(e·d) + z·c, an affine map with
  determinant c·(e × d). Areas therefore scale by c·|sin α|, α the angle between e and d:

      facade area = map area of P / (c·|sin α|)

  i.e. the vertical extent is scaled by 1/c and the horizontal extent is taken
  perpendicular to d (w = s·sin α) and brought back to the facade by 1/|sin α|. e comes from
  the polygon's first edge, which must be horizontal on the facade (its base or eave line:
  z constant there, so its image runs along e). A facade seen edge-on (|sin α| < 0.05) is
  refused.

Coordinates are map CRS metres, float64; pixel coordinates (column, row) follow GDAL's
convention: (0, 0) is the top-left corner of the top-left pixel.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

from pipeline25d.core.errors import InputFileError, MeasureError
from pipeline25d.core.grid import Grid
from pipeline25d.geometry.camera import horizontal_direction, relief_factor
from pipeline25d.geometry.perspectives import ID_PATTERN, Perspective

MIN_SIN_FACADE = 0.05   # facades closer than ~3° to the view direction are seen edge-on


class MapInfo(NamedTuple):
    """A map's perspective and its north-up pixel grid."""

    path: Path
    perspective: Perspective
    grid: Grid

    @property
    def gsd(self) -> float:
        """Metres per pixel."""
        return float(self.grid.res)


class Height(NamedTuple):
    """A vertical edge measured on a map: metres, and the pair's offset across d."""

    height: float          # (T − B)·d / cot φ
    off_m: float           # |(T − B) × d|, metres on the map
    off_deg: float         # angle between T − B and d
    per_px: float          # height change per pixel of click error along d (gsd / cot φ)


def open_map(path: str | Path) -> MapInfo:
    """The perspective (from the file name ``<id>.tif``, else the ``perspective`` of the
    ``<stem>.json`` beside it) and the grid of a map COG."""
    from pipeline25d.analysis.evaluate.rasters import _open

    path = Path(path)
    grid = Grid.of_dataset(_open(path))
    if re.fullmatch(ID_PATTERN, path.stem):
        return MapInfo(path, Perspective.from_id(path.stem), grid)
    meta = path.with_suffix(".json")
    try:
        pid = json.loads(meta.read_text())["perspective"]["id"]
        return MapInfo(path, Perspective.from_id(pid), grid)
    except (OSError, ValueError, KeyError, TypeError):
        raise InputFileError(path, f"no perspective: the name is not like az045_el45.tif and {meta.name} "
                                   "beside it does not give perspective.id") from None


def pixel_to_map(info: MapInfo, cols_rows: np.ndarray) -> np.ndarray:
    """(n, 2) pixel (column, row) -> (n, 2) float64 map coordinates."""
    px = np.asarray(cols_rows, dtype=np.float64).reshape(-1, 2)
    return np.column_stack(info.grid.xy(px[:, 0], px[:, 1]))


def _cot(p: Perspective) -> float:
    if p.elevation == 90:
        raise MeasureError(f"{p.id} is a nadir map (elevation 90°): vertical edges have no length on it, "
                           "so heights and facades cannot be measured; use an oblique map")
    return relief_factor(p)


def measure_height(base: np.ndarray, top: np.ndarray, p: Perspective, gsd: float) -> Height:
    """The height of a vertical edge from its base and top, (2,) map coordinates each."""
    c = _cot(p)
    d = horizontal_direction(p)
    v = np.asarray(top, dtype=np.float64) - np.asarray(base, dtype=np.float64)
    along = float(v @ d)
    across = float(v[0] * d[1] - v[1] * d[0])
    return Height(along / c, abs(across), math.degrees(math.atan2(abs(across), along)), gsd / c)


def ground_length(points: np.ndarray) -> float:
    """Length (m) of the polyline through (n, 2) ground points, n ≥ 2."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(pts) < 2:
        raise MeasureError("a length needs at least two points")
    return float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())


def facade_area(points: np.ndarray, p: Perspective) -> float:
    """Area (m²) of a facade polygon, (n, 2) map points, n ≥ 3, first edge horizontal on the facade."""
    c = _cot(p)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(pts) < 3:
        raise MeasureError("a facade area needs at least three points")
    rel = pts - pts[0]
    map_area = 0.5 * abs(float(np.sum(rel[:-1, 0] * rel[1:, 1] - rel[1:, 0] * rel[:-1, 1])))
    edge = rel[1]
    if not np.linalg.norm(edge):
        raise MeasureError("the facade polygon's first edge has no length")
    d = horizontal_direction(p)
    sin_a = abs(float(edge[0] * d[1] - edge[1] * d[0])) / float(np.linalg.norm(edge))
    if sin_a < MIN_SIN_FACADE:
        raise MeasureError(f"the facade's first edge runs within {math.degrees(math.asin(sin_a)):.1f}° of the "
                           f"view direction ({p.id}): it is seen edge-on; measure it on another perspective")
    return map_area / (c * sin_a)


def describe(info: MapInfo, kind: str, points: np.ndarray) -> str:
    """One line of text for ``python -m pipeline25d measure``."""
    try:
        return _describe(info, kind, points)
    except MeasureError as exc:
        raise MeasureError(f"{info.path}: {exc}") from None


def _describe(info: MapInfo, kind: str, points: np.ndarray) -> str:
    p = info.perspective
    head = f"{info.path.name} (azimuth {p.azimuth}°, elevation {p.elevation}°, gsd {info.gsd:g} m):"
    if kind == "height":
        if len(points) != 2:
            raise MeasureError(f"a height needs exactly two points (base, top), got {len(points)}")
        h = measure_height(points[0], points[1], p, info.gsd)
        note = "" if h.height >= 0 else " (negative: the top lies before the base along the view; swap them?)"
        return (f"{head} height {h.height:.2f} m{note}, ±{h.per_px:.2f} m per pixel of click error; "
                f"the pair is {h.off_m:.2f} m ({h.off_deg:.1f}°) off the view direction")
    if kind == "length":
        return f"{head} ground length {ground_length(points):.2f} m"
    if kind == "facade":
        return f"{head} facade area {facade_area(points, p):.1f} m²"
    raise MeasureError(f"unknown measurement {kind!r} (height, length or facade)")
