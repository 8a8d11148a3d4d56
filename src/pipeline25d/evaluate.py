"""Independent check of orthorectification: ground offsets of an oblique map against the nadir map.

The nadir map (az000_el90) is exact for ground by construction, so wherever ground is visible
in both, an oblique map's ground should sit on the same map coordinates. This module measures
by how much it does not, by image correlation on square ground windows; it uses neither the
pipeline's GCPs nor its warp scores.

Sign convention: an offset (dx_px, dy_px) says where the oblique map shows the ground relative
to where the nadir map shows it, in map pixels, x east and y NORTH. A ground feature that the
nadir map shows at map coordinates (X, Y) appears in the oblique map at
(X + dx_px·gsd, Y + dy_px·gsd). (Rows grow southwards, so dy_px = −Δrow.)

CLI::

    python -m pipeline25d.evaluate ground OBLIQUE.tif [OBLIQUE2.tif ...] NADIR.tif \
        [--dsm DSM.tif --dtm DTM.tif] [--json out.json]
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

from .errors import CRSError, InputFileError, Pipeline25dError
from .raster import gdal

log = logging.getLogger(__name__)

GroundMaskFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""(x, y) map coordinates in metres (2-D arrays, one window's pixel centres) -> bool array, True = ground."""

MIN_OK_WINDOWS = 10           # fewer ok windows than this: no summary figures ("n/a")
_ALIGN_TOL_PX = 1e-3          # origins closer than this to a whole-pixel offset count as aligned
_GSD_RTOL = 1e-6
_GREY = np.array([0.299, 0.587, 0.114])


@dataclass
class OffsetResult:
    """Ground offsets of one oblique map against the nadir map.

    Per-window arrays cover every correlated window (``n_windows`` of them, ok or failed):
    ``x``, ``y`` window centre in map coordinates (metres, nadir position), ``dx_px``/``dy_px``
    offset in map pixels (x east, y north; see module docstring), ``quality`` normalised
    cross-correlation of the aligned windows (−1..1), ``peak_ratio`` second/first peak of the
    phase-correlation surface, ``ok`` whether the window passed, ``reason`` why not ('' if ok).
    Summary figures use ok windows only and are None with fewer than MIN_OK_WINDOWS.
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
    n_transparent: int            # excluded: some pixel not fully opaque in either map
    n_flat: int                   # excluded: grey std <= min_texture in either map
    n_not_ground: int             # excluded: not ground per ground_mask_fn
    x: np.ndarray = field(repr=False)
    y: np.ndarray = field(repr=False)
    dx_px: np.ndarray = field(repr=False)
    dy_px: np.ndarray = field(repr=False)
    quality: np.ndarray = field(repr=False)
    peak_ratio: np.ndarray = field(repr=False)
    ok: np.ndarray = field(repr=False)
    reason: list[str] = field(repr=False)

    @property
    def n_windows(self) -> int:
        return int(len(self.ok))

    @property
    def n_ok(self) -> int:
        return int(np.count_nonzero(self.ok))

    @property
    def n_failed(self) -> int:
        return self.n_windows - self.n_ok

    def summary(self) -> dict[str, Any]:
        """Counts plus rms/median/p95 of the offset length and the mean vector (bias), px and m."""
        out: dict[str, Any] = {"n_windows": self.n_windows, "n_ok": self.n_ok, "n_failed": self.n_failed,
                               "failed_by_reason": {r: self.reason.count(r) for r in sorted(set(self.reason)) if r}}
        keys = ("rms", "median", "p95", "bias_x", "bias_y")
        if self.n_ok < MIN_OK_WINDOWS:
            out.update({f"{k}_{u}": None for k in keys for u in ("px", "m")})
            return out
        dx, dy = self.dx_px[self.ok], self.dy_px[self.ok]
        length = np.hypot(dx, dy)
        px = {"rms": float(np.sqrt(np.mean(length ** 2))), "median": float(np.median(length)),
              "p95": float(np.percentile(length, 95)), "bias_x": float(dx.mean()), "bias_y": float(dy.mean())}
        for k in keys:
            out[f"{k}_px"] = round(px[k], 4)
            out[f"{k}_m"] = round(px[k] * self.gsd_m, 4)
        return out

    def summary_line(self) -> str:
        """One line, e.g. ``az045_el45: 812 windows, 790 ok, rms 0.31 px (0.08 m), p95 0.60 px,
        bias (+0.02, -0.05) px``; "n/a (N windows)" instead of figures from < MIN_OK_WINDOWS ok windows."""
        s = self.summary()
        line = f"{self.name}: {self.n_windows} windows, {self.n_ok} ok, "
        if s["rms_px"] is None:
            line += f"n/a ({self.n_ok} windows)"
        else:
            line += (f"rms {s['rms_px']:.2f} px ({s['rms_m']:.2f} m), p95 {s['p95_px']:.2f} px, "
                     f"bias ({s['bias_x_px']:+.2f}, {s['bias_y_px']:+.2f}) px")
        excluded = [f"{n} {what}" for n, what in ((self.n_transparent, "transparent"), (self.n_flat, "flat"),
                                                  (self.n_not_ground, "not ground")) if n]
        if excluded:
            line += "; excluded " + ", ".join(excluded)
        if self.resampled:
            line += "; oblique resampled onto the nadir grid"
        return line

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: settings, counts, summary and the per-window columns."""
        return {
            "name": self.name, "oblique": self.oblique, "nadir": self.nadir, "gsd_m": self.gsd_m,
            "window_px": self.window_px, "step_px": self.step_px, "resampled": self.resampled, "note": self.note,
            "n_grid": self.n_grid, "n_examined": self.n_examined, "n_transparent": self.n_transparent,
            "n_flat": self.n_flat, "n_not_ground": self.n_not_ground,
            "summary": self.summary(),
            "windows": {
                "x": [round(float(v), 3) for v in self.x], "y": [round(float(v), 3) for v in self.y],
                "dx_px": [round(float(v), 3) for v in self.dx_px], "dy_px": [round(float(v), 3) for v in self.dy_px],
                "quality": [round(float(v), 4) for v in self.quality],
                "peak_ratio": [round(float(v), 4) for v in self.peak_ratio],
                "ok": [bool(v) for v in self.ok], "reason": list(self.reason),
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
        raise InputFileError(path, f"map must be north-up without rotation, geotransform {gt}")
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
    alpha = arr[3] if n >= 4 else np.full(arr.shape[1:], 255, np.uint8)
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


# --------------------------------------------------------------------------- correlation

def _hann(n: int) -> np.ndarray:
    h = np.hanning(n)
    return np.outer(h, h)


def _peak_ratio(a: np.ndarray, b: np.ndarray, exclude: int = 2) -> float:
    """Second-highest / highest value of the integer phase-correlation surface (peaks ≥ ``exclude`` px apart)."""
    cross = np.fft.fft2(a) * np.conj(np.fft.fft2(b))
    surface = np.real(np.fft.ifft2(cross / (np.abs(cross) + 1e-12)))
    r, c = np.unravel_index(np.argmax(surface), surface.shape)
    p1 = surface[r, c]
    rows = (np.arange(r - exclude, r + exclude + 1) % surface.shape[0])[:, None]
    cols = (np.arange(c - exclude, c + exclude + 1) % surface.shape[1])[None, :]
    rest = surface.copy()
    rest[rows, cols] = -np.inf
    return float(rest.max() / p1) if p1 > 0 else 1.0


def measure_window(nadir_grey: np.ndarray, oblique_grey: np.ndarray, upsample_factor: int = 20,
                   ) -> tuple[float, float, float, float]:
    """Offset of ``oblique_grey`` relative to ``nadir_grey`` (same-size square windows, same map cells).

    Returns (d_col, d_row, ncc, peak_ratio): the oblique content sits at the nadir content's
    pixel position + (d_col, d_row) (rows grow southwards); ncc is the normalised
    cross-correlation after aligning the oblique window by the found shift (interior only).
    """
    from scipy import ndimage
    from skimage.registration import phase_cross_correlation

    n = nadir_grey.shape[0]
    a = (nadir_grey - nadir_grey.mean()) / (nadir_grey.std() + 1e-12)
    b = (oblique_grey - oblique_grey.mean()) / (oblique_grey.std() + 1e-12)
    win = _hann(n)
    # skimage returns the shift that registers the moving (oblique) image onto the reference
    shift, _, _ = phase_cross_correlation(a * win, b * win, upsample_factor=upsample_factor,
                                          normalization="phase")
    ratio = _peak_ratio(a * win, b * win)
    margin = int(math.ceil(np.abs(shift).max())) + 2
    if n - 2 * margin < n // 2:
        return float(-shift[1]), float(-shift[0]), float("nan"), ratio
    aligned = ndimage.shift(b, shift, order=3, mode="nearest")
    inner = (slice(margin, n - margin),) * 2
    ncc = float(np.corrcoef(a[inner].ravel(), aligned[inner].ravel())[0, 1])
    return float(-shift[1]), float(-shift[0]), ncc, ratio


# --------------------------------------------------------------------------- main entry

def ground_offsets(oblique_tif: str | Path, nadir_tif: str | Path, ground_mask_fn: GroundMaskFn | None = None,
                   window_px: int = 64, step_px: int | None = None, min_texture: float = 4.0,
                   max_windows: int = 2000, seed: int = 0, min_ncc: float = 0.5, max_peak_ratio: float = 0.5,
                   max_shift_px: float | None = None, upsample_factor: int = 20) -> OffsetResult:
    """Measure where the oblique map shows the ground relative to the nadir map, window by window.

    Windows of ``window_px``² nadir-grid pixels are cut every ``step_px`` (default: window_px)
    over the overlap of the two maps. A window is used only when every pixel is fully opaque
    (alpha 255) in both maps, its grey std exceeds ``min_texture`` (0–255 grey levels) in both,
    and ``ground_mask_fn`` (if given) says True for every pixel centre. Grid windows are visited
    in a seeded random order until ``max_windows`` are used. Each is correlated by sub-pixel
    phase correlation (Hann-windowed, normalised grey, ``upsample_factor``); a window fails
    (counted, never dropped) when the aligned NCC < ``min_ncc`` ('low_correlation'), the
    phase-correlation surface has a second peak > ``max_peak_ratio`` × the first
    ('ambiguous_peak') or the shift exceeds ``max_shift_px`` (default window_px/4,
    'shift_too_large'). Maps must share the CRS. An oblique origin off the nadir grid by a
    fraction of a pixel is handled exactly (nearest-pixel pairing plus the known fraction); a
    different gsd makes the oblique map be resampled bilinearly onto the nadir grid (noted).
    """
    step_px = int(step_px or window_px)
    max_shift_px = window_px / 4 if max_shift_px is None else max_shift_px
    nad, obl = _open(nadir_tif), _open(oblique_tif)
    if not _same_crs(nad.GetProjection(), obl.GetProjection()):
        raise CRSError(f"{oblique_tif} and {nadir_tif} are in different CRSs")
    gn = nad.GetGeoTransform()
    gsd = gn[1]
    pair = _pair_grids(obl, nad, oblique_tif)
    src, (oc, orow), (nc, nr), (w, h) = pair.src, pair.obl_off, pair.nad_off, pair.size

    cols = np.arange(0, w - window_px + 1, step_px) if w >= window_px else np.zeros(0, int)
    rows = np.arange(0, h - window_px + 1, step_px) if h >= window_px else np.zeros(0, int)
    grid = [(int(r), int(c)) for r in rows for c in cols]
    order = np.random.default_rng(seed).permutation(len(grid))
    centre = (np.arange(window_px) + 0.5)

    counts = {"transparent": 0, "flat": 0, "not_ground": 0}
    out: dict[str, list] = {k: [] for k in ("x", "y", "dx", "dy", "q", "pr", "ok", "reason")}
    n_examined = 0
    for i in order:
        if len(out["ok"]) >= max_windows:
            break
        n_examined += 1
        r, c = grid[i]
        gn_grey, an = _read_window(nad, nc + c, nr + r, window_px)
        if (an != 255).any():
            counts["transparent"] += 1
            continue
        go_grey, ao = _read_window(src, oc + c, orow + r, window_px)
        if (ao != 255).any():
            counts["transparent"] += 1
            continue
        if gn_grey.std() <= min_texture or go_grey.std() <= min_texture:
            counts["flat"] += 1
            continue
        xs = gn[0] + (nc + c + centre) * gsd
        ys = gn[3] + (nr + r + centre) * gn[5]
        if ground_mask_fn is not None:
            xx, yy = np.meshgrid(xs, ys)
            if not np.asarray(ground_mask_fn(xx, yy), bool).all():
                counts["not_ground"] += 1
                continue
        d_col, d_row, ncc, ratio = measure_window(gn_grey, go_grey, upsample_factor)
        if math.hypot(d_col, d_row) > max_shift_px or not np.isfinite(ncc):
            reason = "shift_too_large"
        elif ncc < min_ncc:
            reason = "low_correlation"
        elif ratio > max_peak_ratio:
            reason = "ambiguous_peak"
        else:
            reason = ""
        out["x"].append(float(xs.mean()))
        out["y"].append(float(ys.mean()))
        out["dx"].append(d_col + pair.frac[0])
        out["dy"].append(-(d_row + pair.frac[1]))
        out["q"].append(ncc)
        out["pr"].append(ratio)
        out["ok"].append(not reason)
        out["reason"].append(reason)

    f = lambda k: np.asarray(out[k], dtype=float)  # noqa: E731
    return OffsetResult(
        name=Path(oblique_tif).stem, oblique=str(oblique_tif), nadir=str(nadir_tif), gsd_m=float(gsd),
        window_px=window_px, step_px=step_px, resampled=pair.resampled, note=pair.note,
        n_grid=len(grid), n_examined=n_examined, n_transparent=counts["transparent"], n_flat=counts["flat"],
        n_not_ground=counts["not_ground"], x=f("x"), y=f("y"), dx_px=f("dx"), dy_px=f("dy"),
        quality=f("q"), peak_ratio=f("pr"), ok=np.asarray(out["ok"], dtype=bool), reason=out["reason"])


def ground_mask_from_rasters(dsm_tif: str | Path, dtm_tif: str | Path, max_height: float = 0.5,
                             dilate_m: float = 1.0, map_crs: str | None = None) -> GroundMaskFn:
    """A ground_mask_fn from a surface and a terrain model (GeoTIFFs, heights in metres).

    Ground is where DSM − DTM < ``max_height`` (metres); non-ground (and nodata) is grown by
    ``dilate_m`` metres so window edges next to buildings and trees are not counted as ground.
    The DTM is sampled bilinearly at the DSM's cell centres (any CRS pyproj knows). The
    returned function looks up the nearest DSM cell for map coordinates (x, y) in
    ``map_crs`` (default: the DSM's CRS); outside the DSM it says False.
    """
    from scipy import ndimage

    from .crs import transform_points
    from .raster import DTM

    try:
        ds = gdal().Open(str(dsm_tif))
    except RuntimeError as exc:
        raise InputFileError(dsm_tif, f"cannot open as a raster: {exc}") from None
    gt = ds.GetGeoTransform()
    if gt[2] or gt[4]:
        raise InputFileError(dsm_tif, "rotated geotransforms are not supported")
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
    with np.errstate(invalid="ignore"):
        ground = (dsm - terrain) < max_height
    radius = int(math.ceil(dilate_m / min(abs(gt[1]), abs(gt[5]))))
    if radius > 0:
        ground = ~ndimage.maximum_filter(~ground, size=2 * radius + 1, mode="nearest")
    reproject = bool(map_crs) and bool(dsm_wkt) and not _same_crs(map_crs, dsm_wkt)

    def is_ground(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x, y = np.asarray(x, float), np.asarray(y, float)
        if reproject:
            pts = transform_points(np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)]), map_crs, dsm_wkt)
            x, y = pts[:, 0].reshape(x.shape), pts[:, 1].reshape(y.shape)
        col = np.floor((x - gt[0]) / gt[1]).astype(np.int64)
        row = np.floor((y - gt[3]) / gt[5]).astype(np.int64)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        out = np.zeros(x.shape, bool)
        out[inside] = ground[row[inside], col[inside]]
        return out

    return is_ground


# --------------------------------------------------------------------------- CLI

def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m pipeline25d.evaluate", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("ground", help="ground offsets of oblique maps against the nadir map (image correlation)")
    p.add_argument("maps", nargs="+", metavar="MAP.tif", help="one or more oblique maps, then the nadir map last")
    p.add_argument("--dsm", help="surface model GeoTIFF (with --dtm: only windows on ground are used)")
    p.add_argument("--dtm", help="terrain model GeoTIFF")
    p.add_argument("--max-height", type=float, default=0.5, help="ground: DSM - DTM below this (m)")
    p.add_argument("--window", type=int, default=64, help="window size (px)")
    p.add_argument("--step", type=int, default=None, help="window spacing (px, default: window)")
    p.add_argument("--min-texture", type=float, default=4.0, help="minimum grey std in a window (0-255)")
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
    try:
        mask = None
        if args.dsm:
            mask = ground_mask_from_rasters(args.dsm, args.dtm, args.max_height,
                                            map_crs=_open(nadir).GetProjection() or None)
        results = {}
        for path in obliques:
            if Path(path).resolve() == Path(nadir).resolve():
                continue
            res = ground_offsets(path, nadir, mask, window_px=args.window, step_px=args.step,
                                 min_texture=args.min_texture, max_windows=args.max_windows, seed=args.seed)
            key = res.name if res.name not in results else path
            results[key] = res
            print(res.summary_line(), flush=True)
    except (Pipeline25dError, RuntimeError) as exc:
        print(f"evaluate: error: {exc}", file=sys.stderr)
        return 1
    if args.json:
        from .atomic import write_json

        write_json(args.json, {"nadir": nadir, "dsm": args.dsm, "dtm": args.dtm,
                               "maps": {k: r.to_dict() for k, r in results.items()}})
    return 0


if __name__ == "__main__":
    sys.exit(main())
