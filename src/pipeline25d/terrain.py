"""Terrain from the model itself: a nadir height map (DSM), ground cells, an interpolated DTM.

1. **DSM**: the scene rendered straight down, tile by tile, through the tile renderer's
   depth pass (no multisampling, so each cell holds the model's top surface exactly at
   its centre; 24-bit depth over the scene's height range).
2. **Ground**: an input's own terrain where it has one (CityJSON TINRelief or ground
   semantics); elsewhere the Cloth Simulation Filter (Zhang et al. 2016,
   ``cloth-simulation-filter``, maintained by the method's authors). CSF is run on the DSM
   minus a smooth lower envelope (a grey opening wider than the largest above-ground
   object, then a Gaussian), so steep relief does not tear the cloth: on a 1 km test with
   600 m of relief this lifts ground recall from 0.92–0.95 to 1.00 with no object cell
   taken as ground.
3. **DTM**: ground cells keep the DSM's height; the rest (under buildings, trees) is filled
   by GDAL's inverse-distance ``FillNodata``.
All heights are float64 metres in the scene CRS; the rasters are written as float32 GeoTIFFs.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .raster import gdal

log = logging.getLogger(__name__)

DSM_TILE_PX = 2048          # render tile edge of the DSM pass
MAX_DSM_CELLS = 16_000_000  # the auto resolution coarsens until the DSM has at most this many cells
NADIR_MARGIN_M = 1.0        # depth-range margin of the nadir pass


@dataclass(frozen=True)
class Grid:
    """A north-up raster grid: top-left corner (xmin, ymax), square cells of ``res`` metres."""

    xmin: float
    ymax: float
    res: float
    width: int
    height: int

    @classmethod
    def covering(cls, bounds_xy: tuple[float, float, float, float], res: float) -> "Grid":
        """The grid of ``res`` cells aligned to multiples of ``res`` that covers the bounds."""
        xmin, ymin, xmax, ymax = bounds_xy
        x0, y0 = math.floor(xmin / res) * res, math.floor(ymin / res) * res
        x1, y1 = math.ceil(xmax / res) * res, math.ceil(ymax / res) * res
        return cls(x0, y1, res, max(1, round((x1 - x0) / res)), max(1, round((y1 - y0) / res)))

    @property
    def geotransform(self) -> tuple[float, ...]:
        return (self.xmin, self.res, 0.0, self.ymax, 0.0, -self.res)

    @property
    def bounds_xy(self) -> tuple[float, float, float, float]:
        return (self.xmin, self.ymax - self.height * self.res, self.xmin + self.width * self.res, self.ymax)

    def cell_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(height, width) float64 x and y of every cell centre."""
        xs = self.xmin + (np.arange(self.width) + 0.5) * self.res
        ys = self.ymax - (np.arange(self.height) + 0.5) * self.res
        return np.meshgrid(xs, ys)


def auto_resolution(bounds_xy: tuple[float, float, float, float], gsd: float) -> float:
    """DSM/DTM cell size: 2·gsd clamped to [0.5, 5] m, coarsened to keep the grid under MAX_DSM_CELLS."""
    res = min(max(2.0 * gsd, 0.5), 5.0)
    area = (bounds_xy[2] - bounds_xy[0]) * (bounds_xy[3] - bounds_xy[1])
    while area / res ** 2 > MAX_DSM_CELLS:
        res *= 2
    return res


# -- DSM ------------------------------------------------------------------------------------
def render_height_map(chunks: list[tuple[np.ndarray, Callable[[], tuple[np.ndarray, list]]]], grid: Grid,
                      tile_px: int = DSM_TILE_PX) -> np.ndarray:
    """Top-surface height (float64, NaN where no model) at every cell centre of ``grid``.

    ``chunks``: (bounds (2, 3), load) per chunk, load() -> (origin, parts); a DSM tile loads
    only the chunks whose footprint touches it, so memory stays O(tile) beyond the output.
    """
    from .camera import Extent
    from .perspectives import Perspective
    from .render import TileRenderer, TileView, create_context

    nadir = Perspective(0, 90)
    out = np.full((grid.height, grid.width), np.nan)
    if not chunks:
        return out
    zlo = min(b[0][2] for b, _ in chunks) - NADIR_MARGIN_M
    zhi = max(b[1][2] for b, _ in chunks) + NADIR_MARGIN_M
    ctx = create_context()
    try:
        renderer = TileRenderer(ctx, samples=0)
        for r0 in range(0, grid.height, tile_px):
            for c0 in range(0, grid.width, tile_px):
                h, w = min(tile_px, grid.height - r0), min(tile_px, grid.width - c0)
                x0, y1 = grid.xmin + c0 * grid.res, grid.ymax - r0 * grid.res
                ext = Extent(x0, y1 - h * grid.res, x0 + w * grid.res, y1)
                todo = [load() for b, load in chunks
                        if b[0][0] <= ext.xmax and b[1][0] >= ext.xmin and b[0][1] <= ext.ymax and b[1][1] >= ext.ymin]
                if not todo:
                    continue
                # nadir depth is −z: near = the highest surface
                view = TileView(nadir, 0.0, ext, (-zhi, -zlo), (w, h))
                depth = renderer.render_depth(todo, view)
                out[r0:r0 + h, c0:c0 + w] = -depth
    finally:
        ctx.release()
    return out


# -- ground classification -------------------------------------------------------------------
def lower_envelope(dsm: np.ndarray, res: float, max_object_m: float) -> np.ndarray:
    """A smooth surface under the DSM: grey opening wider than any object, then a Gaussian.

    Planes and gentle curvature pass through an opening unchanged; objects narrower than
    ``max_object_m`` are removed. NaN cells are filled with the nearest value first.
    """
    from scipy import ndimage as ndi

    filled = fill_nearest(dsm)
    k = max(3, int(math.ceil(max_object_m / res)) | 1)
    opened = ndi.grey_opening(filled, size=(k, k))
    return ndi.gaussian_filter(opened, sigma=k / 6)


def fill_nearest(values: np.ndarray) -> np.ndarray:
    """NaN cells take the value of the nearest finite cell (all-NaN input stays NaN)."""
    bad = ~np.isfinite(values)
    if not bad.any() or bad.all():
        return values.copy()
    from scipy import ndimage as ndi   # only when needed: tile jobs read DTMs without holes

    idx = ndi.distance_transform_edt(bad, return_distances=False, return_indices=True)
    return values[tuple(idx)]


def csf_ground(dsm: np.ndarray, grid: Grid, max_object_m: float, cloth_resolution: float,
               rigidness: int, class_threshold: float) -> np.ndarray:
    """Boolean mask of ground cells by the Cloth Simulation Filter on the detrended DSM."""
    import CSF

    valid = np.isfinite(dsm)
    if not valid.any():
        return valid
    residual = dsm - lower_envelope(dsm, grid.res, max_object_m)
    xs, ys = grid.cell_centres()
    pts = np.column_stack([xs[valid] - grid.xmin, ys[valid] - grid.ymax, residual[valid]])
    csf = CSF.CSF()
    csf.params.bSloopSmooth = True
    csf.params.cloth_resolution = cloth_resolution
    csf.params.rigidness = rigidness
    csf.params.class_threshold = class_threshold
    csf.params.interations = 500
    csf.params.time_step = 0.65
    csf.setPointCloud(pts)
    ground, off = CSF.VecInt(), CSF.VecInt()
    csf.do_filtering(ground, off, exportCloth=False)
    flat = np.zeros(int(valid.sum()), dtype=bool)
    flat[np.asarray(ground, dtype=np.int64)] = True
    mask = np.zeros_like(valid)
    mask[valid] = flat
    return mask


def trim_object_edges(ground: np.ndarray, dsm: np.ndarray | None = None, tol: float = 0.1,
                      window: int = 7) -> np.ndarray:
    """Drop the ground cells along objects that rise above the ground around them.

    A ground cell touching a non-ground cell is a wall foot or eave on a surface mesh, or
    true ground where a model's wall meets its terrain. With ``dsm`` it is kept when it
    lies at most ``tol`` m above the plane fitted (least squares) to the inner ground cells
    of a ``window``² neighbourhood, so the ground at a building's foot still shapes the DTM
    under it. Without ``dsm`` (or with too few inner cells to fit) every edge cell is dropped.
    """
    from scipy import ndimage as ndi

    edge = ground & ndi.binary_dilation(~ground, structure=np.ones((3, 3), bool))
    inner = ground & ~edge
    if dsm is None:
        return inner
    h, w = ground.shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    r0, c0 = rows - rows.mean(), cols - cols.mean()     # centred: keeps the sums well conditioned
    wgt = inner.astype(np.float64)
    z = np.where(inner, dsm, 0.0)

    def box(a):
        return ndi.uniform_filter(a, size=window, mode="constant")

    # local plane z = a + b·row + c·col by weighted least squares (3×3 normal equations per cell)
    terms = [wgt, wgt * r0, wgt * c0, wgt * r0 * r0, wgt * r0 * c0, wgt * c0 * c0]
    s0, sr, sc, srr, src, scc = (box(t) for t in terms)
    tz, trz, tcz = box(z), box(z * r0), box(z * c0)
    keep = inner.copy()
    idx = np.nonzero(edge & (s0 * window ** 2 >= 6))
    if len(idx[0]):
        # the normal equations of the edge cells only (a whole-grid (h, w, 3, 3) stack is 9 grids)
        rows_of_normal = ((s0, sr, sc), (sr, srr, src), (sc, src, scc))
        m = np.stack([np.stack([a[idx] for a in row], -1) for row in rows_of_normal], -2)
        v = np.stack([tz[idx], trz[idx], tcz[idx]], -1)
        ok = np.abs(np.linalg.det(m)) > 1e-9 * np.maximum(s0[idx], 1e-12) ** 3
        coef = np.zeros((len(m), 3))
        coef[ok] = np.linalg.solve(m[ok], v[ok][..., None])[..., 0]
        plane = coef[:, 0] + coef[:, 1] * r0[idx] + coef[:, 2] * c0[idx]
        keep[idx[0][ok], idx[1][ok]] = dsm[idx][ok] <= plane[ok] + tol
    return keep


# -- DTM --------------------------------------------------------------------------------------
def interpolate_dtm(seed: np.ndarray, search_cells: int) -> np.ndarray:
    """Fill the NaN cells of ``seed`` (ground heights) with GDAL's inverse-distance FillNodata.

    The search reaches ``search_cells`` (half the widest object is enough); cells beyond it
    take their nearest value. A change to the ground therefore alters the DTM only within
    that reach, which keeps district updates local.
    """
    g = gdal()
    h, w = seed.shape
    if not np.isfinite(seed).any():
        raise ValueError("no ground cells to build a DTM from")
    nodata = -1e30
    ds = g.GetDriverByName("MEM").Create("", w, h, 1, g.GDT_Float64)
    band = ds.GetRasterBand(1)
    band.SetNoDataValue(nodata)
    band.WriteArray(np.where(np.isfinite(seed), seed, nodata))
    g.FillNodata(band, None, maxSearchDist=max(int(search_cells), 1), smoothingIterations=0)
    out = band.ReadAsArray().astype(np.float64)
    out[out <= nodata / 2] = np.nan      # FillNodata works in float32: unfilled cells read float32(-1e30)
    return fill_nearest(out)


def write_float_geotiff(path: str | Path, values: np.ndarray, grid: Grid, wkt: str) -> None:
    """An (h, w) float raster as a tiled, deflated float32 GeoTIFF (NaN nodata), atomically."""
    g = gdal()
    with atomic_path(path) as tmp:
        ds = g.GetDriverByName("GTiff").Create(str(tmp), grid.width, grid.height, 1, g.GDT_Float32,
                                               ["COMPRESS=DEFLATE", "PREDICTOR=3", "TILED=YES"])
        ds.SetGeoTransform(grid.geotransform)
        ds.SetProjection(wkt)
        band = ds.GetRasterBand(1)
        band.SetNoDataValue(float("nan"))
        band.WriteArray(values.astype(np.float32))
        ds.FlushCache()
        ds = None


def read_float_geotiff(path: str | Path) -> tuple[np.ndarray, Grid]:
    """Inverse of :func:`write_float_geotiff` (float64 values, NaN nodata)."""
    ds = gdal().Open(str(path))
    gt = ds.GetGeoTransform()
    values = ds.GetRasterBand(1).ReadAsArray().astype(np.float64)
    return values, Grid(gt[0], gt[3], gt[1], ds.RasterXSize, ds.RasterYSize)
