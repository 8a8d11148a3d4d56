"""Building footprints from any OGR vector file, as float64 rings in the scene CRS, and their rasters."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline25d.core.errors import CRSError, InputFileError
from pipeline25d.core.grid import Grid, Window


@dataclass(frozen=True)
class Footprint:
    """A building footprint: ``rings`` are (n, 2) float64 x/y vertex arrays (not closed).

    Rings are filled by the even-odd rule: exterior rings, holes and the parts of a
    multipolygon may come in any order.
    """

    id: str
    rings: tuple[np.ndarray, ...]

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax)."""
        xy = np.concatenate(self.rings)
        return (float(xy[:, 0].min()), float(xy[:, 1].min()), float(xy[:, 0].max()), float(xy[:, 1].max()))


log = logging.getLogger(__name__)


def _srs(text_or_wkt: str):
    from osgeo import osr

    srs = osr.SpatialReference()
    srs.SetFromUserInput(text_or_wkt)
    srs.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
    return srs


def read_footprints(path: str | Path, layer: str | None = None, id_field: str | None = None,
                    crs: str | None = None) -> list[Footprint]:
    """Polygon and multipolygon footprints (holes kept) from any OGR vector file.

    ``layer``: layer name (default: the first layer with polygon geometries). ``id_field``:
    attribute holding the building id (default: the feature id). ``crs`` (WKT or e.g.
    'EPSG:28992'): the scene CRS to reproject to when the layer's differs; a layer without
    a CRS is taken to be in it. Curved geometries are linearised; features without a
    polygon (or with an empty id) are skipped with a warning. Raises InputFileError naming
    the file for an unreadable file, a missing layer or field, or no polygon layer, and
    CRSError naming it when the layer cannot be transformed to ``crs``.
    """
    from osgeo import ogr, osr

    ogr.UseExceptions()
    path = Path(path)
    if not path.exists():
        raise InputFileError(path, "no such file")
    try:
        ds = ogr.Open(str(path))
    except RuntimeError as exc:
        raise InputFileError(path, f"cannot open as a vector file: {exc}") from None
    if ds is None:
        raise InputFileError(path, "cannot open as a vector file")
    names = [ds.GetLayerByIndex(i).GetName() for i in range(ds.GetLayerCount())]
    if layer is not None:
        lyr = ds.GetLayerByName(layer)
        if lyr is None:
            raise InputFileError(path, f"no layer {layer!r} (layers: {', '.join(names) or 'none'})")
        if not _is_polygon_layer(lyr):
            raise InputFileError(path, f"layer {layer!r} holds no polygons")
    else:
        lyr = next((ds.GetLayerByIndex(i) for i in range(ds.GetLayerCount())
                    if _is_polygon_layer(ds.GetLayerByIndex(i))), None)
        if lyr is None:
            raise InputFileError(path, f"no polygon layer (layers: {', '.join(names) or 'none'})")
    defn = lyr.GetLayerDefn()
    if id_field is not None and defn.GetFieldIndex(id_field) < 0:
        fields = [defn.GetFieldDefn(i).GetName() for i in range(defn.GetFieldCount())]
        raise InputFileError(path, f"layer {lyr.GetName()!r} has no field {id_field!r} (fields: {', '.join(fields)})")

    transform = None
    src_srs = lyr.GetSpatialRef()
    if crs and src_srs is not None:
        src_srs = src_srs.Clone()
        src_srs.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
        try:
            dst_srs = _srs(crs)
        except RuntimeError as exc:
            raise CRSError(f"{path}: unknown target CRS {crs!r}: {exc}") from None
        if not src_srs.IsSame(dst_srs):
            try:
                transform = osr.CoordinateTransformation(src_srs, dst_srs)
            except RuntimeError as exc:
                raise CRSError(f"{path}: cannot transform layer {lyr.GetName()!r} to the scene CRS: {exc}") from None
    elif crs and src_srs is None:
        log.warning("%s: layer %r has no CRS; taken to be the scene CRS", path, lyr.GetName())

    out: list[Footprint] = []
    skipped = 0
    lyr.ResetReading()
    for feat in lyr:
        geom = feat.GetGeometryRef()
        fid = feat.GetField(id_field) if id_field is not None else feat.GetFID()
        if geom is None or fid is None or str(fid) == "":
            skipped += 1
            continue
        geom = geom.Clone()
        if geom.HasCurveGeometry():
            geom = geom.GetLinearGeometry()
        if transform is not None:
            try:
                geom.Transform(transform)
            except RuntimeError as exc:
                raise CRSError(f"{path}: cannot transform feature {fid} to the scene CRS: {exc}") from None
        rings = _rings(geom)
        if not rings:
            skipped += 1
            continue
        out.append(Footprint(str(fid), tuple(rings)))
    if skipped:
        log.warning("%s: %d features without a polygon or id skipped", path, skipped)
    return out


def _is_polygon_layer(lyr) -> bool:
    from osgeo import ogr

    gt = ogr.GT_Flatten(lyr.GetGeomType())
    if gt in (ogr.wkbPolygon, ogr.wkbMultiPolygon, ogr.wkbCurvePolygon, ogr.wkbMultiSurface):
        return True
    if gt in (ogr.wkbUnknown, ogr.wkbGeometryCollection):
        lyr.ResetReading()
        for i, feat in enumerate(lyr):
            g = feat.GetGeometryRef()
            if g is not None and _rings(g.GetLinearGeometry() if g.HasCurveGeometry() else g):
                lyr.ResetReading()
                return True
            if i >= 100:
                break
        lyr.ResetReading()
    return False


def _rings(geom) -> list[np.ndarray]:
    """Every ring of every polygon in ``geom`` as (n, 2) float64 (closing vertex dropped)."""
    from osgeo import ogr

    gt = ogr.GT_Flatten(geom.GetGeometryType())
    if gt == ogr.wkbPolygon:
        rings = []
        for i in range(geom.GetGeometryCount()):
            pts = np.asarray(geom.GetGeometryRef(i).GetPoints() or [], dtype=np.float64)
            if len(pts) and np.array_equal(pts[0], pts[-1]):
                pts = pts[:-1]
            if len(pts) >= 3:
                rings.append(np.ascontiguousarray(pts[:, :2]))
        return rings
    if gt in (ogr.wkbMultiPolygon, ogr.wkbGeometryCollection):
        return [r for i in range(geom.GetGeometryCount()) for r in _rings(geom.GetGeometryRef(i))]
    return []


def contains(footprint: Footprint, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Even-odd point-in-footprint test for arrays of points."""
    out = np.zeros(np.shape(x), bool)
    for ring in footprint.rings:
        for a, b in zip(ring, np.roll(ring, -1, axis=0)):
            if a[1] == b[1]:
                continue
            out ^= ((a[1] > y) != (b[1] > y)) & (x < (b[0] - a[0]) * (y - a[1]) / (b[1] - a[1]) + a[0])
    return out


def rasterize(footprint: Footprint, grid: Grid, win: Window) -> np.ndarray:
    """(height, width) bool: pixels of the window ``win`` of ``grid`` whose centres are inside (even-odd)."""
    from skimage.draw import polygon

    mask = np.zeros((win.height, win.width), dtype=bool)
    for ring in footprint.rings:
        cols, rows = grid.colrow(ring[:, 0], ring[:, 1])
        rr, cc = polygon(rows - 0.5 - win.row0, cols - 0.5 - win.col0, shape=mask.shape)
        ring_mask = np.zeros_like(mask)
        ring_mask[rr, cc] = True
        mask ^= ring_mask
    return mask

@dataclass
class RefBuilding:
    """A building the model knows: roof z (scene CRS metres; NaN if unknown), roof kind, ridge z
    (gabled roofs), and its own ground z where the model has one (NaN otherwise)."""

    footprint: Footprint | None
    roof_z: float
    kind: str = "flat"
    ridge_z: float = math.nan
    own_ground_z: float = math.nan
    extra: dict = field(default_factory=dict)


def inside_points(fp: Footprint, step: float, margin: float = 0.0) -> np.ndarray:
    """(n, 2) points of a ``step`` grid inside the footprint, at least ``margin`` from its outline
    (tested at ± margin along x and y); the centroid of the vertices if the grid misses it."""
    xmin, ymin, xmax, ymax = fp.bounds
    xs = np.arange(xmin + step / 2, xmax, step)
    ys = np.arange(ymin + step / 2, ymax, step)
    gx, gy = (a.ravel() for a in np.meshgrid(xs, ys))
    keep = contains(fp, gx, gy)
    for dx, dy in ((margin, 0), (-margin, 0), (0, margin), (0, -margin)) if margin > 0 else ():
        keep &= contains(fp, gx + dx, gy + dy)
    if not keep.any():
        c = np.concatenate(fp.rings).mean(axis=0)
        return c[None]
    return np.column_stack([gx[keep], gy[keep]])
