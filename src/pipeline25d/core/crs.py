"""CRS parsing and coordinate transforms (pyproj), cached and always x/y ordered."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from pipeline25d.core.errors import CRSError

ECEF = "EPSG:4978"


@lru_cache(maxsize=64)
def parse_crs(text: str):
    """pyproj.CRS for ``text`` (e.g. 'EPSG:28992'); raises CRSError when unknown."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError as PyprojCRSError

    try:
        return CRS.from_user_input(text)
    except PyprojCRSError as exc:
        raise CRSError(f"unknown CRS {text!r}: {exc}") from None


def check_scene_crs(text: str) -> None:
    """Raise CRSError unless ``text`` is a projected CRS with metre axes."""
    crs = parse_crs(text)
    horizontal = crs.sub_crs_list[0] if crs.is_compound else crs
    if not horizontal.is_projected:
        raise CRSError(f"scene crs {text!r} is not a projected CRS (metres are needed)")
    units = {ax.unit_name for ax in horizontal.axis_info[:2]}
    if not units <= {"metre", "meter", "m"}:
        raise CRSError(f"scene crs {text!r} has axis units {sorted(units)}, not metres")


def is_geographic(text: str) -> bool:
    """Whether the horizontal part of ``text`` is a geographic CRS (degrees of latitude and longitude)."""
    crs = parse_crs(text)
    return (crs.sub_crs_list[0] if crs.is_compound else crs).is_geographic


def horizontal_wkt(text: str) -> str:
    """WKT of the horizontal part of ``text`` (what a GeoTIFF of the map carries)."""
    crs = parse_crs(text)
    if crs.is_compound:
        crs = crs.sub_crs_list[0]
    return crs.to_wkt()


@lru_cache(maxsize=64)
def transformer(src: str, dst: str):
    """The cached pyproj Transformer from ``src`` to ``dst`` (3D, x/y order); CRSError when there is none."""
    from pyproj import Transformer

    try:
        return Transformer.from_crs(parse_crs(src).to_3d(), parse_crs(dst).to_3d(), always_xy=True)
    except Exception as exc:  # pyproj raises several types here
        raise CRSError(f"cannot transform {src} to {dst}: {exc}") from None


@lru_cache(maxsize=64)
def z_unit(text: str) -> tuple[str, float]:
    """(name, metres) of the unit heights are written in under CRS ``text``: its vertical axis's
    (a compound or 3D CRS), a 2D projected CRS's horizontal unit (it names no vertical one, and
    its models write heights as they write x and y: New York City's buildings in EPSG:2263 have
    z in US survey feet), else metres (a 2D geographic CRS)."""
    crs = parse_crs(text)
    axes = crs.axis_info
    if len(axes) >= 3 or (crs.is_projected and axes):
        axis = axes[2] if len(axes) >= 3 else axes[0]
        return axis.unit_name, float(axis.unit_conversion_factor)
    return "metre", 1.0


def implied_z_metres(text: str) -> float:
    """Metres per unit of the heights pyproj takes as metres in ``text``: a 2D CRS's (its
    :func:`z_unit`); pyproj converts a vertical axis's unit itself."""
    return z_unit(text)[1] if len(parse_crs(text).axis_info) == 2 else 1.0


def transform_points(points: np.ndarray, src: str, dst: str) -> np.ndarray:
    """(n, 3) float64 points from CRS ``src`` to ``dst``; z carried as height, in each CRS's
    :func:`z_unit` (a 2D CRS in feet: z in feet).

    Raises CRSError when the transform fails or yields non-finite coordinates
    (typically a model far outside the target CRS's area of use).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if parse_crs(src) == parse_crs(dst):
        return pts.copy()
    x, y, z = transformer(src, dst).transform(pts[:, 0], pts[:, 1], pts[:, 2] * implied_z_metres(src))
    out = np.column_stack([x, y, z / implied_z_metres(dst)])
    if not np.isfinite(out).all():
        raise CRSError(f"transforming {len(pts)} points from {src} to {dst} gave non-finite values")
    return out


def check_within_area_of_use(points_lonlat: np.ndarray, dst: str, where: str) -> None:
    """Raise CRSError when lon/lat points lie outside ``dst``'s area of use (with 1° slack)."""
    area = parse_crs(dst).area_of_use
    if area is None or len(points_lonlat) == 0:
        return
    lon, lat = points_lonlat[:, 0], points_lonlat[:, 1]
    slack = 1.0
    if (lon.min() < area.west - slack or lon.max() > area.east + slack
            or lat.min() < area.south - slack or lat.max() > area.north + slack):
        raise CRSError(
            f"{where}: model at lon {lon.min():.4f}..{lon.max():.4f}, lat {lat.min():.4f}..{lat.max():.4f} "
            f"lies outside the area of use of {dst} ({area.name})"
        )


def east_north_up_axes(points: np.ndarray) -> np.ndarray:
    """(k, 3, 3) east, north and up unit vectors (columns) at (k, 3) ECEF points, as CesiumJS's
    ``eastNorthUpToFixedFrame`` makes them: up along the WGS 84 ellipsoid's normal by the point's
    own coordinates (x/a², y/a², z/b²), east = z × up, north = up × east; at a pole, east is +y."""
    from pyproj import Geod

    geod = Geod(ellps="WGS84")
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    up = points / np.array([geod.a ** 2, geod.a ** 2, geod.b ** 2])
    up /= np.linalg.norm(up, axis=1, keepdims=True)
    east = np.column_stack([-points[:, 1], points[:, 0], np.zeros(len(points))])
    length = np.linalg.norm(east, axis=1, keepdims=True)
    east = np.where(length > 0, east / np.where(length > 0, length, 1.0), [0.0, 1.0, 0.0])
    return np.stack([east, np.cross(up, east), up], axis=2)
