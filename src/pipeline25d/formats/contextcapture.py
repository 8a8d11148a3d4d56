"""ContextCapture / Bentley iTwin Capture ``metadata.xml`` (SRS and SRS origin of a model).

Exported meshes (OBJ, OSGB, 3MX ...) hold coordinates relative to ``SRSOrigin`` in the CRS
named by ``SRS``::

    <ModelMetadata version="1">
        <SRS>EPSG:32633</SRS>
        <SRSOrigin>500000,4000000,0</SRSOrigin>
    </ModelMetadata>

``SRS`` may also be ``ENU:lat,lon``: a local east-north-up frame tangent to the WGS 84
ellipsoid at (lat, lon, h = 0). PROJ's ``+proj=topocentric`` string works on geocentric
input and cannot serve as a CRS for geographic transforms, so that frame is returned as
WKT2 of a projected CRS with the EPSG method "Geographic/topocentric conversions"
(9837), which :func:`pipeline25d.core.crs.transform_points` and ``check_scene_crs`` accept.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from pipeline25d.core.crs import parse_crs
from pipeline25d.core.errors import CRSError, InputFileError, UnsupportedFeatureError

_ENU = re.compile(r"^\s*ENU\s*:\s*([-+0-9.eE]+)\s*,\s*([-+0-9.eE]+)\s*$", re.IGNORECASE)


def read_metadata_xml(path: str | Path) -> tuple[str, np.ndarray]:
    """(CRS text for :mod:`pipeline25d.core.crs`, float64 (3,) SRS origin) of a metadata.xml.

    A missing ``SRSOrigin`` means (0, 0, 0). Raises InputFileError for unreadable or
    malformed files, UnsupportedFeatureError for an SRS that cannot be interpreted.
    """
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except FileNotFoundError:
        raise InputFileError(path, "metadata.xml is missing") from None
    except (ET.ParseError, OSError) as exc:
        raise InputFileError(path, f"cannot parse metadata XML: {exc}") from None
    if _local(root.tag) != "ModelMetadata":
        raise InputFileError(path, f"root element is <{_local(root.tag)}>, not <ModelMetadata>")
    srs = _child_text(root, "SRS")
    if not srs:
        raise InputFileError(path, "no <SRS> element")
    return srs_crs_text(srs, path), origin_of(_child_text(root, "SRSOrigin"), path)


def enu_crs_wkt(lat: float, lon: float, height: float = 0.0) -> str:
    """WKT2 of a topocentric east-north-up CRS at (lat, lon, ellipsoidal height) on WGS 84."""
    deg = 'ANGLEUNIT["degree",0.0174532925199433]'
    metre = 'LENGTHUNIT["metre",1]'
    return (
        f'PROJCRS["ENU {lat:.9g},{lon:.9g}",'
        'BASEGEOGCRS["WGS 84",DATUM["World Geodetic System 1984",'
        f'ELLIPSOID["WGS 84",6378137,298.257223563,{metre}]],PRIMEM["Greenwich",0,{deg}],ID["EPSG",4979]],'
        'CONVERSION["ENU",METHOD["Geographic/topocentric conversions",ID["EPSG",9837]],'
        f'PARAMETER["Latitude of topocentric origin",{lat!r},{deg},ID["EPSG",8834]],'
        f'PARAMETER["Longitude of topocentric origin",{lon!r},{deg},ID["EPSG",8835]],'
        f'PARAMETER["Ellipsoidal height of topocentric origin",{height!r},{metre},ID["EPSG",8836]]],'
        'CS[Cartesian,3],'
        f'AXIS["topocentric East (U)",east,ORDER[1],{metre}],'
        f'AXIS["topocentric North (V)",north,ORDER[2],{metre}],'
        f'AXIS["topocentric height (W)",up,ORDER[3],{metre}]]'
    )


def srs_crs_text(srs: str, path: Path) -> str:
    """CRS text for an SRS value: EPSG codes/WKT as given, ENU:lat,lon as topocentric WKT."""
    srs = srs.strip()
    enu = _ENU.match(srs)
    if enu:
        lat, lon = float(enu.group(1)), float(enu.group(2))
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 360.0):
            raise InputFileError(path, f"ENU origin {lat}, {lon} is not a latitude, longitude")
        return enu_crs_wkt(lat, lon)
    if srs.upper().startswith("ENU"):
        raise UnsupportedFeatureError(path, f"SRS {srs!r}: only the form 'ENU:lat,lon' is supported")
    try:
        parse_crs(srs)
    except CRSError as exc:
        raise UnsupportedFeatureError(path, f"SRS {srs!r} is not a CRS pyproj understands ({exc})") from None
    return srs


def origin_of(text: str | None, path: Path) -> np.ndarray:
    """float64 (3,) from 'x,y,z' (2 values: z = 0; absent: zeros)."""
    if not text:
        return np.zeros(3)
    try:
        values = [float(v) for v in re.split(r"[,\s]+", text.strip()) if v]
    except ValueError:
        raise InputFileError(path, f"SRSOrigin {text!r} is not numbers") from None
    if len(values) not in (2, 3) or not np.all(np.isfinite(values)):
        raise InputFileError(path, f"SRSOrigin {text!r} is not 'x,y,z'")
    return np.array(values + [0.0] * (3 - len(values)), dtype=np.float64)


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _child_text(root: ET.Element, name: str) -> str | None:
    for child in root:
        if _local(child.tag) == name:
            return (child.text or "").strip()
    return None
