"""The report's pictures: map thumbnails (read from the COGs' overviews), check-point residual
vectors over them, and measured building heights against their reference.

Each picture is made in memory and returned as encoded bytes (WEBP thumbnails, PNG plots) for
:mod:`pipeline25d.publish.report_html` to embed; nothing is fetched from outside. Plots use
matplotlib's object API (Figure + Agg canvas), never pyplot's global state.
"""

from __future__ import annotations

import csv
import io
import math
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline25d.core.grid import Extent, Grid
from pipeline25d.core.raster import dataset_bounds, gdal
from pipeline25d.stages.gcps import read_observations
from pipeline25d.stages.maps.warp import predict

THUMB_PX = 480                       # longest side of a map thumbnail
ARROW_SHARE = 0.08                   # the largest residual arrow is drawn about this share of the map's width


@dataclass(frozen=True)
class Thumbnail:
    """A map reduced to at most THUMB_PX a side: its RGBA pixels, WEBP bytes and world extent."""

    rgba: np.ndarray                 # (h, w, 4) uint8
    webp: bytes
    extent: Extent


def thumbnail(cog: str | Path, size: int = THUMB_PX) -> Thumbnail:
    """The map ``cog`` at most ``size`` pixels a side (GDAL reads its overviews, so the cost does not grow
    with the map)."""
    g = gdal()
    ds = g.Open(str(cog))
    w, h = ds.RasterXSize, ds.RasterYSize
    scale = min(1.0, size / max(w, h))
    small = g.Translate("", ds, format="MEM", width=max(1, round(w * scale)), height=max(1, round(h * scale)),
                        resampleAlg="average")
    name = f"/vsimem/thumb_{uuid.uuid4().hex}.webp"
    try:
        g.GetDriverByName("WEBP").CreateCopy(name, small, options=["QUALITY=80"])
        f = g.VSIFOpenL(name, "rb")
        g.VSIFSeekL(f, 0, 2)
        n = g.VSIFTellL(f)
        g.VSIFSeekL(f, 0, 0)
        data = bytes(g.VSIFReadL(1, n, f))
        g.VSIFCloseL(f)
    finally:
        g.Unlink(name)
    rgba = np.moveaxis(small.ReadAsArray(), 0, -1)
    if rgba.shape[2] == 3:
        rgba = np.dstack([rgba, np.full(rgba.shape[:2], 255, np.uint8)])
    return Thumbnail(rgba.astype(np.uint8), data, dataset_bounds(ds))


@dataclass(frozen=True)
class Residuals:
    """Check points of one map: their true (x, y) and the map's error there, (map position − true), metres."""

    xy: np.ndarray                   # (n, 2)
    dxy: np.ndarray                  # (n, 2)


def check_residuals(gcps_csv: str | Path, mosaic: str | Path, method: str, order: int) -> Residuals:
    """Where the map puts each check point, minus where it is: the warp ``method``/``order`` the warp job chose,
    fitted on the GCPs of ``gcps_csv`` on the ``mosaic``'s pixel grid, as the warp job scores it."""
    obs = read_observations(gcps_csv)
    train = [r for r in obs if r.role == "gcp"]
    check = [r for r in obs if r.role == "check"]
    xy = np.array([[r.x, r.y] for r in check], dtype=np.float64).reshape(-1, 2)
    if not check:
        return Residuals(xy, xy.copy())
    grid = Grid.of_dataset(gdal().Open(str(mosaic))) if method != "none" else None
    return Residuals(xy, predict(method, order, train, check, grid) - xy)


def nice_number(v: float) -> float:
    """The largest of 1, 2, 5 × 10^k not above ``v`` (> 0)."""
    k = 10.0 ** math.floor(math.log10(v))
    return max(m * k for m in (1, 2, 5) if m * k <= v * (1 + 1e-12))


def exaggeration(res: Residuals, extent: Extent) -> float:
    """How many times the residual arrows are drawn longer than they are: the largest drawn about
    ARROW_SHARE of the map's width (a 1-2-5 number; 1 where the residuals are that large already)."""
    lengths = np.hypot(*res.dxy.T)
    longest = float(lengths[np.isfinite(lengths)].max(initial=0.0))
    if not longest > 0:
        return 1.0
    return max(1.0, nice_number(ARROW_SHARE * (extent.xmax - extent.xmin) / longest))


def _png(fig) -> bytes:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    out = io.BytesIO()
    fig.savefig(out, format="png", dpi=100)
    return out.getvalue()


def residual_figure(thumb: Thumbnail, res: Residuals, title: str, gsd: float):
    """The map thumbnail with each check point's residual as an arrow from the true position, ``exaggeration``
    times longer than it is (said in the key): a matplotlib Figure whose Quiver holds X, Y (true x, y) and
    U, V (the residual in metres)."""
    from matplotlib.figure import Figure

    e = thumb.extent
    fig = Figure(figsize=(4.8, 4.8 * min(1.4, (e.ymax - e.ymin) / (e.xmax - e.xmin)) + 0.5))
    ax = fig.add_subplot()
    ax.imshow(thumb.rgba, extent=(e.xmin, e.xmax, e.ymin, e.ymax), interpolation="bilinear")
    ax.set_facecolor("#dde3e8")
    k = exaggeration(res, e)
    ok = np.isfinite(res.dxy).all(axis=1)
    if ok.any():
        q = ax.quiver(res.xy[ok, 0], res.xy[ok, 1], res.dxy[ok, 0], res.dxy[ok, 1], angles="xy", scale_units="xy",
                      scale=1 / k, color="#ffd24d", edgecolor="#222", linewidth=0.5, width=0.006, zorder=3)
        ax.plot(res.xy[ok, 0], res.xy[ok, 1], "o", ms=2.5, color="#d00", zorder=4)
        ref = nice_number(float(np.hypot(*res.dxy[ok].T).max()) or gsd)
        ax.quiverkey(q, 0.02, 1.03, ref, f"{ref:g} m ({ref / gsd:.2g} px), arrows ×{k:g}", labelpos="E",
                     coordinates="axes", fontproperties={"size": 8})
    ax.set_xlim(e.xmin, e.xmax)
    ax.set_ylim(e.ymin, e.ymax)
    ax.set_title(title, fontsize=9, pad=18)
    ax.tick_params(labelsize=6)
    ax.ticklabel_format(useOffset=False, style="plain")
    fig.tight_layout()
    return fig


def residual_plot(thumb: Thumbnail, res: Residuals, title: str, gsd: float) -> bytes:
    """:func:`residual_figure` as PNG bytes."""
    return _png(residual_figure(thumb, res, title, gsd))


@dataclass(frozen=True)
class HeightPoints:
    """Measured buildings with a reference: their ids, reference and measured heights (m), roof kinds, and
    the per-view heights ({view: (reference, measured)} over the buildings that view measured)."""

    ids: tuple[str, ...]
    reference: np.ndarray
    measured: np.ndarray
    roof: tuple[str, ...]
    views: dict[str, tuple[np.ndarray, np.ndarray]]


def height_points(heights_csv: str | Path, views: Sequence[str]) -> HeightPoints:
    """The buildings of the heights stage's CSV that have both a measured height and a reference."""
    def num(v: str | None) -> float:
        return float(v) if v not in (None, "") else math.nan

    with open(heights_csv, newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r.get("height") and r.get("reference")]
    ref = np.array([num(r["reference"]) for r in rows])
    per_view = {}
    for v in views:
        got = np.array([num(r.get(f"height_{v}")) for r in rows])
        ok = np.isfinite(got)
        if ok.any():
            per_view[v] = (ref[ok], got[ok])
    return HeightPoints(tuple(r["id"] for r in rows), ref, np.array([num(r["height"]) for r in rows]),
                        tuple(r.get("roof") or "" for r in rows), per_view)


def heights_figure(pts: HeightPoints):
    """Measured heights (combined over the views, and each view's) against their reference, with the 1:1 line."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.2, 4.8))
    ax = fig.add_subplot()
    for (view, (r, m)), colour in zip(pts.views.items(), ("#8da0cb", "#fc8d62", "#66c2a5", "#e78ac3", "#a6d854",
                                                           "#ffd92f", "#e5c494", "#b3b3b3")):
        ax.plot(r, m, ".", ms=4, alpha=0.7, color=colour, label=view)
    roof = np.array(pts.roof)
    for kind, marker in (("flat", "o"), ("gabled", "s")):
        sel = roof == kind
        if sel.any():
            ax.plot(pts.reference[sel], pts.measured[sel], marker, ms=5, mfc="none", mec="#222",
                    label=f"combined, {kind} roofs" + (" (vs eave)" if kind == "gabled" else ""))
    other = ~np.isin(roof, ("flat", "gabled"))
    if other.any():
        ax.plot(pts.reference[other], pts.measured[other], "D", ms=4, mfc="none", mec="#222", label="combined")
    lo = float(np.nanmin([pts.reference.min(), pts.measured.min(), 0.0]))
    hi = float(np.nanmax([pts.reference.max(), pts.measured.max()])) * 1.05
    ax.plot([lo, hi], [lo, hi], "-", color="#999", lw=1, zorder=0, label="1:1")
    ax.set_xlim(lo, hi)
    ax.set_ylim(lo, hi)
    ax.set_aspect("equal")
    ax.set_xlabel("reference height (m)")
    ax.set_ylabel("measured on the maps (m)")
    ax.legend(fontsize=7, loc="upper left")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def heights_plot(pts: HeightPoints) -> bytes:
    """:func:`heights_figure` as PNG bytes."""
    return _png(heights_figure(pts))
