"""Independent check of orthorectification: ground offsets of an oblique map against the nadir map.

The nadir map (az000_el90) is exact for ground by construction, so wherever ground is visible
in both, an oblique map's ground should sit on the same map coordinates. This module measures
by how much it does not, by image correlation on square windows of ground; it uses neither the
pipeline's GCPs nor its warp scores.

Which pixels count. A pixel of a window is usable when it is fully opaque (alpha 255) in both
maps and, given a surface and a terrain model (DSM, DTM), it is ground that the oblique view
sees: DSM − DTM below ``max_height``, and not hidden behind anything standing on the ground
along the line of sight toward that view's camera (see :func:`hidden_by_relief`; heights above
the terrain for the pipeline's terrain-relative maps, where terrain never hides terrain,
absolute heights for maps projected onto a plane); everything else, grown by ``dilate_m``, is
masked out. A window is measured when at least ``min_ground_fraction`` of its pixels are usable
and they have texture, so dense cities with narrow streets, trees and holes in the mesh still
yield windows. Without a DSM and DTM only opacity masks pixels.

How a window is measured (no bias toward zero from the mask): the integer shift is the peak of
the masked normalised cross-correlation (Padfield 2012: only usable pixels of both maps enter,
at every trial shift), then a Gauss–Newton (Lucas–Kanade) least-squares fit of the shift, a
gain and an offset on the usable pixels alone refines it to sub-pixel, interpolating the
oblique map with quintic B-splines, until the update is below 1e-3 px. Masked pixels are never
zero-filled and correlated, so identical mask edges in both maps cannot pull the result
toward zero. A window fails (counted with its reason, never dropped) when the fit's normal
matrix is ill-conditioned (texture in one direction only: the aperture problem), the
correlation surface has a second peak nearly as high as the first, the fit does not converge,
the aligned NCC is below ``min_ncc`` or the shift exceeds ``max_shift_px``.

Sign convention: an offset (dx_px, dy_px) says where the oblique map shows the ground relative
to where the nadir map shows it, in map pixels, x east and y NORTH. A ground feature that the
nadir map shows at map coordinates (X, Y) appears in the oblique map at
(X + dx_px·gsd, Y + dy_px·gsd). (Rows grow southwards, so dy_px = −Δrow.)

Perspectives: an oblique map's view (azimuth θ, the compass bearing of the viewing direction,
elevation φ) is read from its file name stem (``az045_el45.tif``) unless given. On the map, a
point h above the ground shows at (x, y) + h·cot φ·(sin θ, cos θ), so whatever stands on the
ground leans along d = (sin θ, cos θ) and hides the ground behind it.

CLI::

    python -m pipeline25d.analysis.evaluate ground OBLIQUE.tif [OBLIQUE2.tif ...] NADIR.tif \
        [--dsm DSM.tif --dtm DTM.tif] [--json out.json] [--window 32] [--min-ground-fraction 0.3] ...
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from pipeline25d.core.errors import ConfigError, CRSError, InputFileError, Pipeline25dError
from pipeline25d.core.raster import gdal, read_rgba_block, window_alpha
from pipeline25d.geometry.perspectives import Perspective

log = logging.getLogger(__name__)

GroundMaskFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""(x, y) map coordinates in metres (2-D arrays, one window's pixel centres) -> bool array, True = ground."""

MIN_OK_WINDOWS = 10           # fewer ok windows than this: no summary figures ("n/a")
_ALIGN_TOL_PX = 1e-3          # origins closer than this to a whole-pixel offset count as aligned
_GSD_RTOL = 1e-6
_GREY = np.array([0.299, 0.587, 0.114])
_SPLINE_ORDER = 5             # B-spline interpolation of the oblique window (quintic: little sub-pixel bias)
_ERODE_PX = 3                 # fitted oblique pixels lie this far inside its usable area (spline support)
_INTERP_MARGIN = _ERODE_PX    # oblique pixels read beyond the search range, for interpolation
_MIN_FIT_PX = 64              # fewer usable pixels than this after erosion: window fails
_LK_TOL_PX = 1e-3             # Gauss-Newton stops when the shift update is below this
_LK_MAX_ITER = 10
_FD_PX = 1e-3                 # step of the central differences of the spline interpolant

FAIL_REASONS = ("too_few_pixels", "ill_conditioned", "no_convergence", "shift_too_large", "low_correlation",
                "ambiguous_peak")   # in the order they are checked


@dataclass
class OffsetResult:
    """Ground offsets of one oblique map against the nadir map.

    Per-window arrays cover every correlated window (``n_windows`` of them, ok or failed):
    ``x``, ``y`` window centre in map coordinates (metres, nadir position), ``dx_px``/``dy_px``
    offset in map pixels (x east, y north; see module docstring), ``quality`` normalised
    cross-correlation of the aligned usable pixels (−1..1), ``peak_ratio`` second-highest /
    highest local maximum of the masked NCC surface, ``ok`` whether the window passed,
    ``reason`` why not ('' if ok), ``ground_fraction`` share of the window's pixels that are
    usable (opaque in both maps and visible ground), ``n_px`` pixels in the fit,
    ``condition`` condition number of the fit's 2×2 shift normal matrix (gain and offset
    eliminated), ``sigma_px`` formal standard error of the shift (larger semi-axis; residuals are
    spatially correlated, so it understates the real error). Summary figures use ok windows
    only and are None with fewer than MIN_OK_WINDOWS.
    """

    name: str
    oblique: str
    nadir: str
    gsd_m: float
    window_px: int
    step_px: int
    resampled: bool
    note: str
    n_grid: int                   # windows on the grid over the overlap
    n_examined: int               # of those, looked at (all, unless max_windows stopped early)
    n_transparent: int            # excluded: < min_ground_fraction of pixels opaque in both maps
    n_flat: int                   # excluded: grey std of the usable pixels <= min_texture in either map
    n_not_ground: int             # excluded: < min_ground_fraction of pixels opaque and visible ground
    x: np.ndarray = field(repr=False)
    y: np.ndarray = field(repr=False)
    dx_px: np.ndarray = field(repr=False)
    dy_px: np.ndarray = field(repr=False)
    quality: np.ndarray = field(repr=False)
    peak_ratio: np.ndarray = field(repr=False)
    ok: np.ndarray = field(repr=False)
    reason: list[str] = field(repr=False)
    ground_fraction: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    n_px: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    condition: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    sigma_px: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    perspective: str = ""         # view whose visible-ground mask was used ('' without a ground model)
    min_ground_fraction: float = 0.3

    @property
    def n_windows(self) -> int:
        return int(len(self.ok))

    @property
    def n_ok(self) -> int:
        return int(np.count_nonzero(self.ok))

    @property
    def n_failed(self) -> int:
        return self.n_windows - self.n_ok

    def failed_by_reason(self) -> dict[str, int]:
        return {r: self.reason.count(r) for r in sorted(set(self.reason)) if r}

    def summary(self) -> dict[str, Any]:
        """Counts plus rms/median/p95 of the offset length and the mean vector (bias), px and m."""
        out: dict[str, Any] = {"n_windows": self.n_windows, "n_ok": self.n_ok, "n_failed": self.n_failed,
                               "failed_by_reason": self.failed_by_reason()}
        keys = ("rms", "median", "p95", "bias_x", "bias_y")
        if self.n_ok < MIN_OK_WINDOWS:
            out.update({f"{k}_{u}": None for k in keys for u in ("px", "m")})
            out["mean_ground_fraction"] = None
            return out
        dx, dy = self.dx_px[self.ok], self.dy_px[self.ok]
        length = np.hypot(dx, dy)
        px = {"rms": float(np.sqrt(np.mean(length ** 2))), "median": float(np.median(length)),
              "p95": float(np.percentile(length, 95)), "bias_x": float(dx.mean()), "bias_y": float(dy.mean())}
        for k in keys:
            out[f"{k}_px"] = round(px[k], 4)
            out[f"{k}_m"] = round(px[k] * self.gsd_m, 4)
        out["mean_ground_fraction"] = (round(float(self.ground_fraction[self.ok].mean()), 3)
                                       if len(self.ground_fraction) == len(self.ok) else None)
        return out

    def summary_line(self) -> str:
        """One line, e.g. ``az045_el45: 812 windows, 790 ok, rms 0.31 px (0.08 m), p95 0.60 px,
        bias (+0.02, -0.05) px``; "n/a (N windows)" instead of figures from < MIN_OK_WINDOWS ok
        windows; then the failures by reason and the excluded grid windows."""
        s = self.summary()
        line = f"{self.name}: {self.n_windows} windows, {self.n_ok} ok, "
        if s["rms_px"] is None:
            line += f"n/a ({self.n_ok} windows)"
        else:
            line += (f"rms {s['rms_px']:.2f} px ({s['rms_m']:.2f} m), p95 {s['p95_px']:.2f} px, "
                     f"bias ({s['bias_x_px']:+.2f}, {s['bias_y_px']:+.2f}) px")
        if s["failed_by_reason"]:
            line += "; failed " + ", ".join(f"{n} {r}" for r, n in s["failed_by_reason"].items())
        excluded = [f"{n} {what}" for n, what in ((self.n_transparent, "transparent"), (self.n_flat, "flat"),
                                                  (self.n_not_ground, "not ground")) if n]
        if excluded:
            line += "; excluded " + ", ".join(excluded)
        if self.resampled:
            line += "; oblique resampled onto the nadir grid"
        return line

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: settings, counts, summary and the per-window columns."""
        def col(values, nd):
            return [None if not np.isfinite(v) else round(float(v), nd) for v in values]

        return {
            "name": self.name, "oblique": self.oblique, "nadir": self.nadir, "gsd_m": self.gsd_m,
            "window_px": self.window_px, "step_px": self.step_px, "resampled": self.resampled, "note": self.note,
            "perspective": self.perspective, "min_ground_fraction": self.min_ground_fraction,
            "n_grid": self.n_grid, "n_examined": self.n_examined, "n_transparent": self.n_transparent,
            "n_flat": self.n_flat, "n_not_ground": self.n_not_ground,
            "summary": self.summary(),
            "windows": {
                "x": col(self.x, 3), "y": col(self.y, 3), "dx_px": col(self.dx_px, 3), "dy_px": col(self.dy_px, 3),
                "quality": col(self.quality, 4), "peak_ratio": col(self.peak_ratio, 4),
                "ok": [bool(v) for v in self.ok], "reason": list(self.reason),
                "ground_fraction": col(self.ground_fraction, 3), "n_px": [int(v) for v in self.n_px],
                "condition": col(self.condition, 2), "sigma_px": col(self.sigma_px, 4),
            },
        }


# --------------------------------------------------------------------------- reading and grids

def _open(path: str | Path):
    try:
        ds = gdal().Open(str(path))
    except RuntimeError as exc:
        raise InputFileError(path, f"cannot open as a raster: {exc}") from None
    gt = ds.GetGeoTransform()
    if gt[2] or gt[4] or gt[1] <= 0 or gt[5] >= 0:
        raise InputFileError(path, f"must be north-up without rotation, geotransform {gt}")
    return ds


def _same_crs(wkt_a: str, wkt_b: str) -> bool:
    if not wkt_a or not wkt_b:
        return wkt_a == wkt_b
    from osgeo import osr

    a, b = osr.SpatialReference(), osr.SpatialReference()
    a.ImportFromWkt(wkt_a)
    b.ImportFromWkt(wkt_b)
    return bool(a.IsSame(b))


def _read_window(ds, col: int, row: int, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(grey float64, alpha uint8) of a size×size block at pixel (col, row); no alpha band = opaque."""
    arr = ds.ReadAsArray(col, row, size, size)
    if arr.ndim == 2:
        arr = arr[None]
    n = arr.shape[0]
    alpha = window_alpha(ds, arr, col, row, size, size)
    grey = np.tensordot(_GREY, arr[:3].astype(np.float64), axes=1) if n >= 3 else arr[0].astype(np.float64)
    return grey, alpha


@dataclass
class _Pairing:
    """How nadir pixels pair with oblique pixels over the overlap of the two maps."""

    src: Any                      # oblique dataset to read (the file, or an in-memory resampled copy)
    obl_off: tuple[int, int]      # (col, row) in ``src`` of the overlap's top-left pixel
    nad_off: tuple[int, int]      # (col, row) in the nadir map of the same pixel
    size: tuple[int, int]         # overlap (width, height), px
    frac: tuple[float, float]     # map position of oblique pixel minus paired nadir pixel, (east, south) px
    resampled: bool
    note: str


def _pair_grids(obl, nad, oblique_path) -> _Pairing:
    """Pair the oblique map's pixels with the nadir grid.

    Same gsd: each nadir pixel pairs with the nearest oblique pixel; a sub-pixel origin offset
    is kept in ``frac`` and added to measured offsets (exact, no resampling). Different gsd:
    the oblique map is resampled bilinearly onto the nadir grid in memory (noted and logged).
    """
    gn, go = nad.GetGeoTransform(), obl.GetGeoTransform()
    gsd_x, gsd_y = gn[1], -gn[5]
    wn, hn, wo, ho = nad.RasterXSize, nad.RasterYSize, obl.RasterXSize, obl.RasterYSize
    same_gsd = abs(go[1] - gn[1]) <= _GSD_RTOL * gsd_x and abs(go[5] - gn[5]) <= _GSD_RTOL * gsd_y
    # oblique origin in nadir pixel coordinates
    c_lo, r_lo = (go[0] - gn[0]) / gsd_x, (gn[3] - go[3]) / gsd_y
    if same_gsd:
        kc, kr = round(c_lo), round(r_lo)
        fc, fr = c_lo - kc, r_lo - kr
        c0, r0 = max(0, kc), max(0, kr)
        w, h = max(0, min(wn, kc + wo) - c0), max(0, min(hn, kr + ho) - r0)
        note = ""
        if abs(fc) > _ALIGN_TOL_PX or abs(fr) > _ALIGN_TOL_PX:
            note = (f"oblique origin off the nadir grid by ({fc:+.3f}, {fr:+.3f}) px (east, south): windows "
                    "paired on the nearest pixels, the fraction added to the offsets (no resampling)")
            log.info("%s: %s", oblique_path, note)
        else:
            fc = fr = 0.0
        return _Pairing(obl, (c0 - kc, r0 - kr), (c0, r0), (w, h), (fc, fr), False, note)
    c_hi, r_hi = (go[0] + wo * go[1] - gn[0]) / gsd_x, (gn[3] - (go[3] + ho * go[5])) / gsd_y
    c0, r0 = max(0, math.ceil(c_lo - _ALIGN_TOL_PX)), max(0, math.ceil(r_lo - _ALIGN_TOL_PX))
    c1, r1 = min(wn, math.floor(c_hi + _ALIGN_TOL_PX)), min(hn, math.floor(r_hi + _ALIGN_TOL_PX))
    w, h = max(0, c1 - c0), max(0, r1 - r0)
    if w == 0 or h == 0:
        return _Pairing(obl, (0, 0), (0, 0), (0, 0), (0.0, 0.0), False, "maps do not overlap")
    bounds = (gn[0] + c0 * gsd_x, gn[3] - r1 * gsd_y, gn[0] + c1 * gsd_x, gn[3] - r0 * gsd_y)
    warped = gdal().Warp("", obl, format="MEM", outputBounds=bounds, width=w, height=h,
                         resampleAlg="bilinear", dstSRS=nad.GetProjection() or None)
    note = (f"oblique gsd {go[1]:g} x {-go[5]:g} m differs from the nadir gsd {gsd_x:g} x {gsd_y:g} m: "
            "resampled bilinearly onto the nadir grid (interpolation can bias sub-pixel offsets)")
    log.warning("%s: %s", oblique_path, note)
    return _Pairing(warped, (0, 0), (c0, r0), (w, h), (0.0, 0.0), True, note)


def _read_block(ds, col: int, row: int, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Like :func:`_read_window`, but the block may reach past the raster: outside is alpha 0, grey 0."""
    w, h = ds.RasterXSize, ds.RasterYSize
    if col >= 0 and row >= 0 and col + size <= w and row + size <= h:
        return _read_window(ds, col, row, size)
    rgb, alpha = read_rgba_block(ds, col, row, size, size)
    return np.tensordot(rgb.astype(np.float64), _GREY, axes=([2], [0])), alpha


# --------------------------------------------------------------------------- visible ground

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

    def __init__(self, values: np.ndarray, geotransform: tuple[float, ...], crs_wkt: str = "",
                 map_crs: str | None = None):
        self.values = np.asarray(values, bool)
        self.gt = tuple(geotransform)
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
        gt, (h, w) = self.gt, self.values.shape
        col = np.floor((x - gt[0]) / gt[1]).astype(np.int64)
        row = np.floor((y - gt[3]) / gt[5]).astype(np.int64)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        out = np.zeros(x.shape, bool)
        out[inside] = self.values[row[inside], col[inside]]
        return out

    def __and__(self, other: "RasterMask") -> "RasterMask":
        return RasterMask(self.values & other.values, self.gt, self.crs_wkt, self.map_crs)


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
        gt = ds.GetGeoTransform()
        band = ds.GetRasterBand(1)
        dsm = band.ReadAsArray().astype(np.float64)
        if band.GetNoDataValue() is not None:
            dsm[dsm == band.GetNoDataValue()] = np.nan
        dsm_wkt = ds.GetProjection()
        dtm = DTM(dtm_tif, dsm_wkt or "")
        h, w = dsm.shape
        if dtm.values.shape == dsm.shape and np.allclose(dtm.gt, gt) and _same_crs(dtm.crs_wkt, dsm_wkt):
            terrain = dtm.values
        else:
            if not dsm_wkt and dtm.crs_wkt:
                raise InputFileError(dsm_tif, "DSM has no CRS but the DTM has one")
            cc, rr = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
            terrain = dtm.sample((gt[0] + cc * gt[1]).ravel(), (gt[3] + rr * gt[5]).ravel()).reshape(h, w)
        self.dsm, self.dtm, self.gt, self.crs_wkt = dsm, terrain, gt, dsm_wkt
        self.map_crs = map_crs
        self.max_height, self.dilate_m, self.projection, self.clearance = max_height, dilate_m, projection, clearance
        self._masks: dict[str, RasterMask] = {}

    def mask(self, perspective: Perspective | str | None = None) -> RasterMask:
        if isinstance(perspective, str):
            perspective = Perspective.from_id(perspective)
        if perspective is None or perspective.elevation >= 90:
            perspective = Perspective(0, 90)
        if perspective.id not in self._masks:
            values = visible_ground(self.dsm, self.dtm, perspective, (self.gt[1], -self.gt[5]), self.max_height,
                                    self.dilate_m, self.projection, self.clearance)
            self._masks[perspective.id] = RasterMask(values, self.gt, self.crs_wkt, self.map_crs)
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


# --------------------------------------------------------------------------- correlation

@dataclass
class WindowFit:
    """One window's registration (see :func:`measure_window`)."""

    d_col: float                  # oblique content sits at the nadir content's position + (d_col, d_row)
    d_row: float
    ncc: float                    # aligned usable pixels, -1..1 (NaN if not fitted)
    peak_ratio: float             # second / first local maximum of the masked NCC surface
    condition: float              # of the 2x2 shift normal matrix (inf: singular)
    sigma_px: float               # formal standard error of the shift (NaN if not fitted)
    n_px: int                     # pixels in the least-squares fit
    reason: str                   # '' or one of FAIL_REASONS (only the geometric ones set here)


def masked_ncc_surface(ref: np.ndarray, ref_ok: np.ndarray, mov: np.ndarray, mov_ok: np.ndarray,
                       min_overlap: float = 0.5) -> np.ndarray:
    """Masked normalised cross-correlation (Padfield 2012) of an n×n ``ref`` inside an
    (n+2m)×(n+2m) ``mov`` at every integer shift s in [−m, m]²: out[m + s_row, m + s_col] is the
    Pearson correlation of ref(x) with mov(x + m + s) over the x usable in both (``ref_ok``,
    ``mov_ok``); −inf where fewer than ``min_overlap`` × the largest overlap are usable, or no
    texture. Only usable pixels enter: nothing is zero-filled and correlated.
    """
    n, big = ref.shape[0], mov.shape[0]
    a_ok, b_ok = ref_ok.astype(np.float64), mov_ok.astype(np.float64)
    a = np.where(ref_ok, ref - ref[ref_ok].mean(), 0.0) if ref_ok.any() else np.zeros_like(ref)
    b = np.where(mov_ok, mov - mov[mov_ok].mean(), 0.0) if mov_ok.any() else np.zeros_like(mov)
    fa = [np.conj(np.fft.rfft2(v, (big, big))) for v in (a_ok, a, a * a)]
    fb = [np.fft.rfft2(v) for v in (b_ok, b, b * b)]

    def corr(i: int, j: int) -> np.ndarray:          # sum_x A_j(x) B_i(x + s), no wrap-around for s in [0, 2m]
        return np.fft.irfft2(fb[i] * fa[j], (big, big))[:big - n + 1, :big - n + 1]

    count = np.rint(corr(0, 0))
    valid = count >= max(min_overlap * count.max(), 1.0)
    count = np.where(valid, count, 1.0)
    sa, sb, saa, sbb, sab = corr(0, 1), corr(1, 0), corr(0, 2), corr(2, 0), corr(1, 1)
    num = sab - sa * sb / count
    den = np.maximum(saa - sa * sa / count, 0.0) * np.maximum(sbb - sb * sb / count, 0.0)
    valid &= den > 1e-9 * max(float(den[valid].max()) if valid.any() else 0.0, 1e-300)
    out = np.full(count.shape, -np.inf)
    out[valid] = np.minimum(num[valid] / np.sqrt(den[valid]), 1.0)
    return out


def _second_peak_ratio(surface: np.ndarray, peak: tuple[int, int]) -> float:
    """Highest local maximum other than ``peak`` / the value at ``peak`` (1 if the peak is not > 0)."""
    from scipy import ndimage

    p1 = surface[peak]
    if not p1 > 0:
        return 1.0
    s = np.where(np.isfinite(surface), surface, -np.inf)
    local = (s == ndimage.maximum_filter(s, size=3, mode="constant", cval=-np.inf)) & np.isfinite(s)
    local[peak] = False
    if not local.any():
        return 0.0
    return float(max(s[local].max(), 0.0) / p1)


def _schur_shift(hess: np.ndarray) -> np.ndarray:
    """The 2x2 shift block of a 4x4 normal matrix with gain and offset eliminated."""
    hss, hsg, hgg = hess[:2, :2], hess[:2, 2:], hess[2:, 2:]
    return hss - hsg @ np.linalg.solve(hgg, hsg.T)


def measure_window(nadir_grey: np.ndarray, nadir_ok: np.ndarray, oblique_grey: np.ndarray, oblique_ok: np.ndarray,
                   search_px: int, max_condition: float = 25.0, min_ncc: float = 0.5) -> WindowFit:
    """Offset of the oblique map's content relative to the nadir window, from usable pixels only.

    ``nadir_grey``/``nadir_ok``: an n×n window and its usable pixels; ``oblique_grey``/
    ``oblique_ok``: the same map cells with a border of ``search_px`` + 3 pixels on every side.
    Integer shift: the peak of :func:`masked_ncc_surface` within ±``search_px`` (a peak on the
    border of that range fails as 'shift_too_large'; a peak below ``min_ncc``/2 fails as
    'low_correlation' at once). Sub-pixel: Gauss–Newton on ``oblique(x + s) = gain·nadir(x) +
    offset`` over the nadir-usable pixels x whose oblique position lies at least 3 px inside the
    oblique's usable area, with quintic B-spline interpolation of the oblique (its unusable pixels
    filled from the nearest usable one, never zero) and the interpolant's own derivatives, until
    the shift update < 1e-3 px (re-choosing the pixels if the shift moves by more than 1 px).
    Fails 'ill_conditioned' when the shift normal matrix (gain/offset eliminated) has condition
    number > ``max_condition`` (texture in one direction only), 'too_few_pixels' with < 64 pixels
    to fit, 'no_convergence' after 10 iterations. Thresholds on the shift's length, the aligned
    NCC and the peak ratio are the caller's (see :func:`ground_offsets`).
    """
    from scipy import ndimage

    n = nadir_grey.shape[0]
    m = search_px
    margin = (oblique_grey.shape[0] - n) // 2
    if margin < m + _ERODE_PX or oblique_grey.shape[0] != n + 2 * margin:
        raise ValueError("oblique block must be the window plus search_px + 3 (or more) on every side")
    crop = slice(margin - m, margin + n + m)
    surface = masked_ncc_surface(nadir_grey, nadir_ok, oblique_grey[crop, crop], oblique_ok[crop, crop])
    if not np.isfinite(surface).any():
        return WindowFit(0.0, 0.0, float("nan"), 1.0, float("inf"), float("nan"), 0, "too_few_pixels")
    peak = np.unravel_index(int(np.argmax(surface)), surface.shape)
    ratio = _second_peak_ratio(surface, peak)
    s0 = np.array(peak, dtype=float) - m                   # (row, col)
    if surface[peak] < min_ncc / 2:                        # hopeless: even half a pixel off would do better
        return WindowFit(s0[1], s0[0], float(surface[peak]), ratio, float("nan"), float("nan"), 0,
                         "low_correlation")

    # fill unusable oblique pixels from the nearest usable one (no zero steps for the spline to ring on)
    idx = ndimage.distance_transform_edt(~oblique_ok, return_distances=False, return_indices=True)
    filled = oblique_grey[tuple(idx)]
    coef = ndimage.spline_filter(filled, order=_SPLINE_ORDER, mode="mirror")
    inside = ndimage.binary_erosion(oblique_ok, structure=np.ones((3, 3), bool), iterations=_ERODE_PX)
    rows, cols = np.nonzero(nadir_ok)

    def sample(rr, cc):
        return ndimage.map_coordinates(coef, [rr, cc], order=_SPLINE_ORDER, mode="mirror", prefilter=False)

    s = s0.copy()
    fit = None
    for _ in range(2):                                     # second round only if s left s0's pixel set
        base = np.rint(s).astype(int)
        pr, pc = rows + margin + base[0], cols + margin + base[1]
        keep = (pr >= 0) & (pr < inside.shape[0]) & (pc >= 0) & (pc < inside.shape[1])
        keep[keep] = inside[pr[keep], pc[keep]]
        r, c = rows[keep] + margin, cols[keep] + margin
        ref = nadir_grey[rows[keep], cols[keep]]
        if len(ref) < _MIN_FIT_PX:
            return WindowFit(s[1], s[0], float("nan"), ratio, float("inf"), float("nan"), int(len(ref)),
                             "too_few_pixels")
        warped = sample(r + s[0], c + s[1])
        # least-squares line warped ≈ gain·ref + offset (closed form: no RankWarning on flat windows)
        var = float(ref.var())
        gain = float(((ref - ref.mean()) * (warped - warped.mean())).mean() / var) if var > 1e-12 else 1.0
        offset = float(warped.mean() - gain * ref.mean())
        converged = False
        for it in range(_LK_MAX_ITER):
            # derivatives of the spline interpolant itself (exact Jacobian: quadratic convergence)
            jr = (sample(r + s[0] + _FD_PX, c + s[1]) - sample(r + s[0] - _FD_PX, c + s[1])) / (2 * _FD_PX)
            jc = (sample(r + s[0], c + s[1] + _FD_PX) - sample(r + s[0], c + s[1] - _FD_PX)) / (2 * _FD_PX)
            resid = warped - gain * ref - offset
            jac = np.column_stack([jr, jc, -ref, -np.ones_like(ref)])
            hess = jac.T @ jac
            if it == 0:
                try:
                    ev = np.linalg.eigvalsh(_schur_shift(hess))
                except np.linalg.LinAlgError:
                    ev = np.zeros(2)
                cond = float(ev[1] / ev[0]) if ev[0] > 1e-12 * max(ev[1], 1e-300) else float("inf")
                if cond > max_condition:
                    return WindowFit(s[1], s[0], float("nan"), ratio, cond, float("nan"), int(len(ref)),
                                     "ill_conditioned")
            step = np.linalg.solve(hess, -(jac.T @ resid))
            s += step[:2]
            gain += step[2]
            offset += step[3]
            warped = sample(r + s[0], c + s[1])
            if np.hypot(step[0], step[1]) < _LK_TOL_PX:
                converged = True
                break
            if np.abs(s).max() > m + 1:                   # wandered off: the integer peak was wrong
                break
        fit = (r, c, ref, warped, gain, offset, hess, converged, cond)
        if np.abs(s - base).max() <= 1 or not converged:
            break
    r, c, ref, warped, gain, offset, hess, converged, cond = fit
    resid = warped - gain * ref - offset
    try:
        cov = np.linalg.inv(_schur_shift(hess)) * float(resid @ resid) / max(len(ref) - 4, 1)
        sigma = float(np.sqrt(max(np.linalg.eigvalsh(cov)[1], 0.0)))
    except np.linalg.LinAlgError:
        sigma = float("nan")
    ncc = float(np.corrcoef(ref, warped)[0, 1]) if ref.std() > 0 and warped.std() > 0 else float("nan")
    reason = "" if converged else "no_convergence"
    if not reason and max(abs(peak[0] - m), abs(peak[1] - m)) >= m:
        reason = "shift_too_large"                          # integer peak on the border of the search range
    return WindowFit(float(s[1]), float(s[0]), ncc, ratio, cond, sigma, int(len(ref)), reason)


# --------------------------------------------------------------------------- main entry

def ground_offsets(oblique_tif: str | Path, nadir_tif: str | Path,
                   ground_mask_fn: GroundModel | GroundMaskFn | None = None, window_px: int = 32,
                   step_px: int | None = None, min_texture: float = 4.0, max_windows: int = 2000, seed: int = 0,
                   min_ncc: float = 0.5, max_peak_ratio: float = 0.95, max_shift_px: float | None = None,
                   min_ground_fraction: float = 0.3, max_condition: float = 25.0,
                   perspective: Perspective | str | None = None) -> OffsetResult:
    """Measure where the oblique map shows the ground relative to the nadir map, window by window.

    Windows of ``window_px``² nadir-grid pixels are cut every ``step_px`` (default: window_px)
    over the overlap of the two maps. A pixel is usable when it is fully opaque (alpha 255) in
    both maps and the ground mask says True for its centre. The mask: a :class:`GroundModel`
    gives ground the oblique view sees (its perspective from ``perspective`` or the oblique file
    name stem, ConfigError if neither names one) and that is ground in the nadir view; a plain
    GroundMaskFn is used as it is, for both maps (``perspective`` is then not used); None: every
    pixel. A window is used when at
    least ``min_ground_fraction`` of its pixels are usable (else excluded as 'transparent' if
    too few are opaque in both maps, 'not ground' otherwise) and the grey std of its usable
    pixels exceeds ``min_texture`` (0–255 grey levels) in both maps (else 'flat'). Grid windows
    are visited in a seeded random order until ``max_windows`` are used. Each used window is
    registered by :func:`measure_window` (masked NCC, then Gauss–Newton with gain and offset)
    and fails (counted, never dropped) as 'too_few_pixels', 'ill_conditioned' (condition >
    ``max_condition``), 'no_convergence', 'shift_too_large' (> ``max_shift_px``, default
    window_px/4), 'low_correlation' (aligned NCC < ``min_ncc``; an integer NCC peak below
    ``min_ncc``/2 fails so before anything else) or 'ambiguous_peak' (second local maximum of
    the NCC surface > ``max_peak_ratio`` × the first), checked in that order. Defaults (window
    32 px, min_ground_fraction 0.3, max_peak_ratio 0.95, max_condition 25) were chosen on the
    Delft LiDAR mesh, where ~13 % of the cells are ground after dilation.
    Maps must share the CRS. An oblique origin off the nadir grid by a fraction of a pixel is
    handled exactly (nearest-pixel pairing plus the known fraction); a different gsd makes the
    oblique map be resampled bilinearly onto the nadir grid (noted).
    """
    step_px = int(step_px or window_px)
    max_shift_px = window_px / 4 if max_shift_px is None else float(max_shift_px)
    search = int(math.ceil(max_shift_px)) + 1
    margin = search + _INTERP_MARGIN
    nad, obl = _open(nadir_tif), _open(oblique_tif)
    if not _same_crs(nad.GetProjection(), obl.GetProjection()):
        raise CRSError(f"{oblique_tif} and {nadir_tif} are in different CRSs")
    view = ""
    mask_fn: GroundMaskFn | None = ground_mask_fn
    if isinstance(ground_mask_fn, GroundModel):
        p = perspective_of(oblique_tif, perspective)
        view = p.id
        mask_fn = ground_mask_fn.mask(None) & ground_mask_fn.mask(p)
    gn = nad.GetGeoTransform()
    gsd = gn[1]
    pair = _pair_grids(obl, nad, oblique_tif)
    src, (oc, orow), (nc, nr), (w, h) = pair.src, pair.obl_off, pair.nad_off, pair.size

    cols = np.arange(0, w - window_px + 1, step_px) if w >= window_px else np.zeros(0, int)
    rows = np.arange(0, h - window_px + 1, step_px) if h >= window_px else np.zeros(0, int)
    grid = [(int(r), int(c)) for r in rows for c in cols]
    order = np.random.default_rng(seed).permutation(len(grid))
    big = window_px + 2 * margin
    centre = np.arange(big) + 0.5 - margin               # block pixel centres, relative to the window
    inner = slice(margin, margin + window_px)
    need = min_ground_fraction * window_px * window_px

    counts = {"transparent": 0, "flat": 0, "not_ground": 0}
    keys = ("x", "y", "dx", "dy", "q", "pr", "ok", "reason", "gf", "npx", "cond", "sig")
    out: dict[str, list] = {k: [] for k in keys}
    n_examined = 0
    for i in order:
        if len(out["ok"]) >= max_windows:
            break
        n_examined += 1
        r, c = grid[i]
        gn_grey, an = _read_window(nad, nc + c, nr + r, window_px)
        opaque_n = an == 255
        if np.count_nonzero(opaque_n) < need:
            counts["transparent"] += 1
            continue
        go_grey, ao = _read_block(src, oc + c - margin, orow + r - margin, big)
        opaque_o = ao == 255
        if np.count_nonzero(opaque_n & opaque_o[inner, inner]) < need:
            counts["transparent"] += 1
            continue
        xs = gn[0] + (nc + c + centre) * gsd
        ys = gn[3] + (nr + r + centre) * gn[5]
        if mask_fn is not None:
            xx, yy = np.meshgrid(xs, ys)
            ground = np.asarray(mask_fn(xx, yy), bool)
        else:
            ground = np.ones((big, big), bool)
        ok_o = opaque_o & ground
        ok_n = opaque_n & ground[inner, inner]
        both = ok_n & ok_o[inner, inner]
        n_both = int(np.count_nonzero(both))
        if n_both < need:
            counts["not_ground"] += 1
            continue
        if gn_grey[both].std() <= min_texture or go_grey[inner, inner][both].std() <= min_texture:
            counts["flat"] += 1
            continue
        fit = measure_window(gn_grey, ok_n, go_grey, ok_o, search, max_condition, min_ncc)
        reason = fit.reason
        if not reason and math.hypot(fit.d_col, fit.d_row) > max_shift_px:
            reason = "shift_too_large"
        if not reason and not fit.ncc >= min_ncc:
            reason = "low_correlation"
        if not reason and fit.peak_ratio > max_peak_ratio:
            reason = "ambiguous_peak"
        out["x"].append(float(xs[inner].mean()))
        out["y"].append(float(ys[inner].mean()))
        out["dx"].append(fit.d_col + pair.frac[0])
        out["dy"].append(-(fit.d_row + pair.frac[1]))
        out["q"].append(fit.ncc)
        out["pr"].append(fit.peak_ratio)
        out["ok"].append(not reason)
        out["reason"].append(reason)
        out["gf"].append(n_both / window_px ** 2)
        out["npx"].append(fit.n_px)
        out["cond"].append(fit.condition)
        out["sig"].append(fit.sigma_px)

    f = lambda k: np.asarray(out[k], dtype=float)  # noqa: E731
    return OffsetResult(
        name=Path(oblique_tif).stem, oblique=str(oblique_tif), nadir=str(nadir_tif), gsd_m=float(gsd),
        window_px=window_px, step_px=step_px, resampled=pair.resampled, note=pair.note,
        n_grid=len(grid), n_examined=n_examined, n_transparent=counts["transparent"], n_flat=counts["flat"],
        n_not_ground=counts["not_ground"], x=f("x"), y=f("y"), dx_px=f("dx"), dy_px=f("dy"),
        quality=f("q"), peak_ratio=f("pr"), ok=np.asarray(out["ok"], dtype=bool), reason=out["reason"],
        ground_fraction=f("gf"), n_px=np.asarray(out["npx"], dtype=int), condition=f("cond"), sigma_px=f("sig"),
        perspective=view, min_ground_fraction=min_ground_fraction)


# --------------------------------------------------------------------------- CLI

def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pipeline25d evaluate", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("ground", help="ground offsets of oblique maps against the nadir map (image correlation)")
    p.add_argument("maps", nargs="+", metavar="MAP.tif", help="one or more oblique maps, then the nadir map last")
    p.add_argument("--dsm", help="surface model GeoTIFF (with --dtm: only ground the view sees is used)")
    p.add_argument("--dtm", help="terrain model GeoTIFF")
    p.add_argument("--max-height", type=float, default=0.5, help="ground: DSM - DTM below this (m)")
    p.add_argument("--dilate", type=float, default=1.0, help="grow non-ground and hidden ground by this (m)")
    p.add_argument("--projection", choices=("terrain", "plane"), default="terrain",
                   help="how the maps were projected: heights above the terrain (default) or above a plane")
    p.add_argument("--clearance", type=float, default=0.2,
                   help="line of sight: a surface must rise this far above it to hide the ground (m)")
    p.add_argument("--perspective", help="view of the (single) oblique map, e.g. az045_el45 "
                                         "(default: from the file name)")
    p.add_argument("--window", type=int, default=32, help="window size (px)")
    p.add_argument("--step", type=int, default=None, help="window spacing (px, default: window)")
    p.add_argument("--min-ground-fraction", type=float, default=0.3,
                   help="share of a window's pixels that must be opaque visible ground")
    p.add_argument("--min-texture", type=float, default=4.0, help="minimum grey std of the usable pixels (0-255)")
    p.add_argument("--min-ncc", type=float, default=0.5, help="minimum NCC after alignment")
    p.add_argument("--max-peak-ratio", type=float, default=0.95, help="maximum second/first NCC peak")
    p.add_argument("--max-condition", type=float, default=25.0,
                   help="maximum condition number of the shift fit (aperture problem)")
    p.add_argument("--max-shift", type=float, default=None, help="maximum offset (px, default: window/4)")
    p.add_argument("--max-windows", type=int, default=2000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", help="write results (summary and per-window offsets) here")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    if len(args.maps) < 2:
        print("evaluate: error: give at least one oblique map and the nadir map", file=sys.stderr)
        return 2
    if bool(args.dsm) != bool(args.dtm):
        print("evaluate: error: --dsm and --dtm go together", file=sys.stderr)
        return 2
    *obliques, nadir = args.maps
    if args.perspective and len(obliques) > 1:
        print("evaluate: error: --perspective needs a single oblique map", file=sys.stderr)
        return 2
    try:
        model = None
        if args.dsm:
            model = GroundModel(args.dsm, args.dtm, args.max_height, args.dilate,
                                map_crs=_open(nadir).GetProjection() or None, projection=args.projection,
                                clearance=args.clearance)
        results = {}
        for path in obliques:
            if Path(path).resolve() == Path(nadir).resolve():
                continue
            res = ground_offsets(path, nadir, model, window_px=args.window, step_px=args.step,
                                 min_texture=args.min_texture, max_windows=args.max_windows, seed=args.seed,
                                 min_ncc=args.min_ncc, max_peak_ratio=args.max_peak_ratio,
                                 max_shift_px=args.max_shift, min_ground_fraction=args.min_ground_fraction,
                                 max_condition=args.max_condition, perspective=args.perspective)
            key = res.name if res.name not in results else path
            results[key] = res
            print(res.summary_line(), flush=True)
    except (Pipeline25dError, RuntimeError) as exc:
        print(f"evaluate: error: {exc}", file=sys.stderr)
        return 1
    if args.json:
        from pipeline25d.core.atomic import write_json

        write_json(args.json, {"nadir": nadir, "dsm": args.dsm, "dtm": args.dtm,
                               "maps": {k: r.to_dict() for k, r in results.items()}})
    return 0


if __name__ == "__main__":
    sys.exit(main())
