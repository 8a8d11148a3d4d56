"""Which pixels are ground that a view sees: DSM − DTM below a height, not hidden along the line of sight."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pipeline25d.analysis.evaluate.rasters import _open, _same_crs
from pipeline25d.core.errors import ConfigError, InputFileError
from pipeline25d.core.grid import Grid
from pipeline25d.geometry.perspectives import Perspective

log = logging.getLogger(__name__)

GroundMaskFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""(x, y) map coordinates in metres (2-D arrays, one window's pixel centres) -> bool array, True = ground."""


def hidden_by_relief(z: np.ndarray, azimuth: float, elevation: float, cell: tuple[float, float],
                     clearance: float = 0.2, oversample: int = 2) -> np.ndarray:
    """Cells whose line of sight toward the camera of view (``azimuth``, ``elevation``) is blocked.

    ``z`` (h, w) are heights on a north-up grid of ``cell`` = (east, south) metres per cell,
    row 0 north; NaN = no surface (blocks nothing). The camera of a view looks along
    d = (sin θ, cos θ) (x east, y north) and down at φ, so the line of sight from the cell
    centre p rises at tan φ toward −d: p is hidden when some surface p − t·d (t > 0) stands
    above it, ``max_t z(p − t·d) − t·tan φ > z(p) + clearance``. Marched exactly along each ray
    with cumulative maxima on a grid rotated to d (samples every cell/``oversample``, nearest
    cell; rays snapped to the nearest sampled line, ≤ cell/(2·oversample) to the side), so the
    cost is O(cells): a 2,000² grid takes one to two seconds. Unknown surface (outside the grid,
    NaN) hides nothing. Elevation 90: nothing is hidden.
    """
    z = np.asarray(z, dtype=np.float64)
    h, w = z.shape
    if elevation >= 90 or h == 0 or w == 0:
        return np.zeros(z.shape, bool)
    cx, cy = float(cell[0]), float(cell[1])
    th, ph = math.radians(azimuth), math.radians(elevation)
    st, ct, tan_phi = math.sin(th), math.cos(th), math.tan(ph)
    # u along d, v across it, metres from the grid's north-west corner (y north, so y = -row·cy)
    xs, ys = np.array([0.0, w * cx, 0.0, w * cx]), np.array([0.0, 0.0, -h * cy, -h * cy])
    uc, vc = xs * st + ys * ct, xs * ct - ys * st
    du = min(cx, cy) / oversample
    u0, v0 = uc.min() - du, vc.min() - du
    nu, nv = int(math.ceil((uc.max() - u0) / du)) + 2, int(math.ceil((vc.max() - v0) / du)) + 2
    flat = np.where(np.isfinite(z), z, -np.inf).astype(np.float32).ravel()
    u = u0 + du * np.arange(nu)
    rise = ((u - u0) * tan_phi).astype(np.float32)
    horizon = np.empty((nv, nu), np.float32)          # running max of z + rise along each line
    chunk = max(1, 1_000_000 // nu)
    for i0 in range(0, nv, chunk):
        v = v0 + du * np.arange(i0, min(nv, i0 + chunk))[:, None]
        col = np.floor((u[None, :] * st + v * ct) / cx).astype(np.int64)
        row = np.floor(-(u[None, :] * ct - v * st) / cy).astype(np.int64)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        g = np.where(inside, flat[np.where(inside, row * w + col, 0)], np.float32(-np.inf)) + rise
        np.maximum.accumulate(g, axis=1, out=horizon[i0:i0 + len(v)])
    hidden = np.zeros(z.shape, bool)
    cc = (np.arange(w) + 0.5) * cx
    rows_per_chunk = max(1, 1_000_000 // w)
    for r0 in range(0, h, rows_per_chunk):
        yy = -(np.arange(r0, min(h, r0 + rows_per_chunk))[:, None] + 0.5) * cy
        up, vp = cc[None, :] * st + yy * ct, cc[None, :] * ct - yy * st
        i = np.rint((vp - v0) / du).astype(np.int64)
        k = np.ceil((up - u0) / du - 1e-6).astype(np.int64) - 1   # last sample strictly before p
        with np.errstate(invalid="ignore"):      # 1 mm: float32 resolution of the running maxima
            hidden[r0:r0 + len(yy)] = (horizon[i, k] - (up - u0) * tan_phi) > z[r0:r0 + len(yy)] + clearance + 1e-3
    return hidden


def visible_ground(dsm: np.ndarray, dtm: np.ndarray, perspective: Perspective | str | None,
                   cell: tuple[float, float], max_height: float = 0.5, dilate_m: float = 1.0,
                   projection: str = "terrain", clearance: float = 0.2) -> np.ndarray:
    """Cells that are ground and that the view ``perspective`` sees (None or nadir: ground alone).

    ``dsm``, ``dtm`` (h, w) metres on the same north-up grid of ``cell`` = (east, south) metres,
    NaN = no data. Ground: DSM − DTM < ``max_height``. Visible: not hidden (see
    :func:`hidden_by_relief`) behind heights ``z`` along the line of sight, where ``z`` is
    DSM − DTM for ``projection="terrain"`` (the pipeline's terrain-relative maps: everything is
    drawn displaced by its height above the ground under it, so terrain never hides terrain and
    an object hides the ground up to its relative height·cot φ behind it) or the DSM itself for
    ``projection="plane"`` (displacement by absolute height). Everything else is grown by
    ``dilate_m`` metres (square), so pixels next to buildings, trees, holes and the edges of
    hidden strips do not count.
    """
    from scipy import ndimage

    if projection not in ("terrain", "plane"):
        raise ConfigError(f"projection must be 'terrain' or 'plane', not {projection!r}")
    dsm, dtm = np.asarray(dsm, dtype=np.float64), np.asarray(dtm, dtype=np.float64)
    rel = dsm - dtm
    with np.errstate(invalid="ignore"):
        ok = rel < max_height
    if isinstance(perspective, str):
        perspective = Perspective.from_id(perspective)
    if perspective is not None and perspective.elevation < 90:
        z = rel if projection == "terrain" else dsm
        ok &= ~hidden_by_relief(z, perspective.azimuth, perspective.elevation, cell, clearance)
    radius = int(math.ceil(dilate_m / min(abs(cell[0]), abs(cell[1]))))
    if radius > 0:
        ok = ~ndimage.maximum_filter(~ok, size=2 * radius + 1, mode="nearest")
    return ok


class RasterMask:
    """A bool raster on a north-up grid, callable as a GroundMaskFn: (x, y) -> nearest cell, False outside.

    ``map_crs`` (if it differs from the raster's CRS ``crs_wkt``): the CRS of the (x, y) asked for.
    """

    def __init__(self, values: np.ndarray, grid: Grid, crs_wkt: str = "", map_crs: str | None = None):
        self.values = np.asarray(values, bool)
        self.grid = grid
        self.crs_wkt = crs_wkt
        self.map_crs = map_crs
        self._reproject = bool(map_crs) and bool(crs_wkt) and not _same_crs(map_crs, crs_wkt)

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x, y = np.asarray(x, float), np.asarray(y, float)
        if self._reproject:
            from pipeline25d.core.crs import transform_points

            pts = transform_points(np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)]),
                                   self.map_crs, self.crs_wkt)
            x, y = pts[:, 0].reshape(x.shape), pts[:, 1].reshape(y.shape)
        h, w = self.values.shape
        col, row = (np.floor(v).astype(np.int64) for v in self.grid.colrow(x, y))
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        out = np.zeros(x.shape, bool)
        out[inside] = self.values[row[inside], col[inside]]
        return out

    def __and__(self, other: "RasterMask") -> "RasterMask":
        return RasterMask(self.values & other.values, self.grid, self.crs_wkt, self.map_crs)


class GroundModel:
    """A surface and a terrain model (GeoTIFFs, metres) giving ground and per-view visible-ground masks.

    The DTM is sampled bilinearly at the DSM's cell centres (any CRS pyproj knows) unless it
    is on the DSM's grid; masks are on the DSM grid and look up map coordinates in ``map_crs``
    (default: the DSM's CRS). ``mask(None)`` is plain ground (the nadir view's visible ground),
    ``mask("az045_el45")`` ground that view sees (see :func:`visible_ground`); masks are cached.
    """

    def __init__(self, dsm_tif: str | Path, dtm_tif: str | Path, max_height: float = 0.5, dilate_m: float = 1.0,
                 map_crs: str | None = None, projection: str = "terrain", clearance: float = 0.2):
        from pipeline25d.core.raster import DTM

        if projection not in ("terrain", "plane"):
            raise ConfigError(f"projection must be 'terrain' or 'plane', not {projection!r}")
        ds = _open(dsm_tif)
        grid = Grid.of_dataset(ds)
        band = ds.GetRasterBand(1)
        dsm = band.ReadAsArray().astype(np.float64)
        if band.GetNoDataValue() is not None:
            dsm[dsm == band.GetNoDataValue()] = np.nan
        dsm_wkt = ds.GetProjection()
        dtm = DTM(dtm_tif, dsm_wkt or "")
        h, w = dsm.shape
        if (dtm.values.shape == dsm.shape and np.allclose(dtm.grid.geotransform, grid.geotransform)
                and _same_crs(dtm.crs_wkt, dsm_wkt)):
            terrain = dtm.values
        else:
            if not dsm_wkt and dtm.crs_wkt:
                raise InputFileError(dsm_tif, "DSM has no CRS but the DTM has one")
            cc, rr = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
            x, y = grid.xy(cc, rr)
            terrain = dtm.sample(x.ravel(), y.ravel()).reshape(h, w)
        self.dsm, self.dtm, self.grid, self.crs_wkt = dsm, terrain, grid, dsm_wkt
        self.map_crs = map_crs
        self.max_height, self.dilate_m, self.projection, self.clearance = max_height, dilate_m, projection, clearance
        self._masks: dict[str, RasterMask] = {}

    def mask(self, perspective: Perspective | str | None = None) -> RasterMask:
        if isinstance(perspective, str):
            perspective = Perspective.from_id(perspective)
        if perspective is None or perspective.elevation >= 90:
            perspective = Perspective(0, 90)
        if perspective.id not in self._masks:
            values = visible_ground(self.dsm, self.dtm, perspective, (self.grid.transform.a, -self.grid.transform.e),
                                    self.max_height, self.dilate_m, self.projection, self.clearance)
            self._masks[perspective.id] = RasterMask(values, self.grid, self.crs_wkt, self.map_crs)
        return self._masks[perspective.id]

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Plain ground (as :func:`ground_mask_from_rasters`)."""
        return self.mask(None)(x, y)


def ground_mask_from_rasters(dsm_tif: str | Path, dtm_tif: str | Path, max_height: float = 0.5,
                             dilate_m: float = 1.0, map_crs: str | None = None) -> GroundMaskFn:
    """A ground_mask_fn from a surface and a terrain model (GeoTIFFs, heights in metres).

    Ground is where DSM − DTM < ``max_height`` (metres); non-ground (and nodata) is grown by
    ``dilate_m`` metres so window edges next to buildings and trees are not counted as ground.
    The DTM is sampled bilinearly at the DSM's cell centres (any CRS pyproj knows). The
    returned function looks up the nearest DSM cell for map coordinates (x, y) in
    ``map_crs`` (default: the DSM's CRS); outside the DSM it says False. It does not know
    what an oblique view hides: use :class:`GroundModel` for that.
    """
    return GroundModel(dsm_tif, dtm_tif, max_height, dilate_m, map_crs).mask(None)


def perspective_of(path: str | Path, perspective: Perspective | str | None = None) -> Perspective:
    """``perspective`` if given, else the one named by the file name stem (``az045_el45.tif``)."""
    if isinstance(perspective, Perspective):
        return perspective
    text = perspective if perspective is not None else Path(path).stem
    try:
        return Perspective.from_id(text)
    except ValueError:
        what = f"perspective {text!r}" if perspective is not None else f"file name stem {text!r}"
        raise ConfigError(f"{path}: cannot tell the view to mask hidden ground for: {what} is not a "
                          "perspective id like az045_el45; name the map so or give the perspective") from None
