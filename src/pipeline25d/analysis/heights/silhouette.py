"""A roof's height from where the building's silhouette ends on an oblique map, whatever its colours.

On a terrain-relative oblique map the ground shows as on the nadir map; a building hides it over
its footprint swept along d by up to its roof's move (walls, then the roof). Beyond the roof's far
edge the ground shows again. So from each point e of the footprint's far outline (outward normal
along d) the oblique map differs from the nadir map along e + s·d for 0 ≤ s ≤ E and agrees beyond:
E / cot φ is the roof's height above the ground the map drew under e. Colours of roof and walls
never enter: the roof may be tinted like its walls, shaded differently from view to view, pitched.

On sloped ground that height varies along the outline (the map subtracts the DTM under each
vertex). With that DTM (the stage has it) each line is :func:`levelled` exactly: its height plus
the ground the map subtracted at its point, minus the mean ground under the footprint. Without
it, one robust plane through the lines of every view (their far outlines differ, so
together they show the slope both ways) gives the roof above a planar ground, and its value at the
footprint's area centroid the roof above the MEAN ground under the footprint: the stage's
definition of a height. A pitched roof's lines give its eave where its far eave is seen and more
at gable and hip ends; the robust fit follows the majority.

Difference D = |oblique − nadir| (RGB, lightly smoothed). A line's end is the first pixel after
which D stays below ``tol`` for ``SETTLE_PX`` pixels, refined to where D crosses half the contrast
between the run and the ground after it. Lines that start on unchanged ground, never end, or run
onto a neighbouring footprint (a shared wall) are left out; other buildings behind the roof
lengthen a line, which the robust fit drops.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from pipeline25d.analysis.heights.results import MatchSettings
from pipeline25d.formats.footprints import Footprint, contains

SETTLE_PX = 3.0        # D below tol this long (px) ends a line
SAMPLE_PX = 0.25       # march step along d (px)
LINE_PX = 0.5          # spacing of the far-outline points (px)
MIN_LINES = 8          # fewer usable lines: not measured
NEIGHBOUR_M = 3.0      # lines running onto another footprint within this (m) are left out
INLIER_PX = 1.5        # a line agrees with a fit within this many pixels of move (at least 0.25 m)
MIN_CONSISTENT = 0.4   # share of a view's lines within its inlier distance of the fitted plane


def far_outline(fp: Footprint, d: np.ndarray, step_m: float, min_cos: float = 0.25) -> np.ndarray:
    """(n, 2) world points every ``step_m`` along the outline edges whose outward normal points
    along d (cos > ``min_cos``), corners left out (a quarter step in from each end)."""
    pts = []
    for ring in fp.rings:
        for a, b in zip(ring, np.roll(ring, -1, axis=0)):
            e = b - a
            length = float(np.hypot(*e))
            if length <= 0:
                continue
            n = np.array([e[1], -e[0]]) / length
            mid = (a + b) / 2 + 1e-3 * n
            if contains(fp, mid[:1], mid[1:])[0]:
                n = -n
            if float(n @ d) <= min_cos:
                continue
            k = max(int(length / step_m), 1)
            t = (np.arange(k) + 0.5) / k
            pts.append(a + t[:, None] * e)
    return np.concatenate(pts) if pts else np.zeros((0, 2))


def _smooth(img: np.ndarray) -> np.ndarray:
    from scipy import ndimage

    return np.stack([ndimage.gaussian_filter(img[:, :, c].astype(np.float32), 0.7) for c in range(3)], axis=-1)


def _diff(rows: np.ndarray, cols: np.ndarray, obl: tuple[np.ndarray, np.ndarray], obl_off: np.ndarray,
          nad: tuple[np.ndarray, np.ndarray], nad_off: np.ndarray, order: int) -> np.ndarray:
    """|oblique − nadir| at window positions (rows, cols), NaN where either has no data; ``order`` 0
    (nearest pixel) or 1 (bilinear)."""
    from scipy import ndimage

    out = None
    ok = np.ones(rows.shape, bool)
    for (rgb, alpha), off, sign in ((obl, obl_off, 1.0), (nad, nad_off, -1.0)):
        r, c = rows + off[0], cols + off[1]
        ri, ci = np.rint(r).astype(np.int64), np.rint(c).astype(np.int64)
        inside = (ri >= 0) & (ri < alpha.shape[0]) & (ci >= 0) & (ci < alpha.shape[1])
        ri, ci = np.where(inside, ri, 0), np.where(inside, ci, 0)
        ok &= inside & (alpha[ri, ci] == 255)
        if order == 0:
            val = rgb[ri, ci].astype(np.float64)
        else:
            val = np.stack([ndimage.map_coordinates(rgb[:, :, ch], [r.ravel(), c.ravel()], order=1, mode="nearest")
                            .reshape(r.shape) for ch in range(3)], axis=-1)
        out = sign * val if out is None else out + sign * val
    d = np.sqrt(np.sum(out ** 2, axis=-1))
    d[~ok] = np.nan
    return d


def line_ends(start: np.ndarray, d_px: np.ndarray, u_max: float, obl: tuple[np.ndarray, np.ndarray],
              obl_off: np.ndarray, nad: tuple[np.ndarray, np.ndarray], nad_off: np.ndarray,
              tol: float) -> np.ndarray:
    """E (m along d, NaN where unusable) of lines from ``start`` (2, n) (nadir-window row, col);
    oblique index = window index + ``obl_off``, nadir index = window index + ``nad_off``.
    Coarse: every pixel, nearest pixels; then the crossing of half the contrast, bilinear, every
    SAMPLE_PX near the first settled pixel."""
    scale = float(np.hypot(*d_px))                     # px per metre of move
    step = 1.0 / scale                                 # one pixel of move (m)
    s = np.arange(0.0, u_max + 4.0 * step, step)
    rows = start[0][:, None] + s[None, :] * d_px[0]
    cols = start[1][:, None] + s[None, :] * d_px[1]
    diff = _diff(rows, cols, obl, obl_off, nad, nad_off, 0)
    low = np.where(np.isfinite(diff), diff < tol, False)
    k_settle = max(int(round(SETTLE_PX)), 1)
    csum = np.concatenate([np.zeros((low.shape[0], 1)), np.cumsum(low, axis=1)], axis=1)
    n_win = low.shape[1] - k_settle + 1
    settled = (csum[:, k_settle:k_settle + n_win] - csum[:, :n_win]) == k_settle
    settled[:, :1] = False                             # the run must have begun one pixel out
    usable = np.isfinite(diff[:, :2]).all(axis=1) & ~low[:, 1]
    first = np.where(settled.any(axis=1), np.argmax(settled, axis=1), -1)
    keep = np.flatnonzero(usable & (first > 1))
    out = np.full(len(start[0]), np.nan)
    if not len(keep):
        return out
    # fine: from 3 px before the first settled pixel to 2 px after it
    fine = np.arange(-3.0, 2.0 + 1e-9, SAMPLE_PX) * step
    sf = s[first[keep]][:, None] + fine[None, :]
    fr = start[0][keep][:, None] + sf * d_px[0]
    fc = start[1][keep][:, None] + sf * d_px[1]
    df = _diff(fr, fc, obl, obl_off, nad, nad_off, 1)
    n_in = int(round(1.5 / SAMPLE_PX))
    for i, k in enumerate(keep):
        row = df[i]
        inside, after = row[:n_in], row[-n_in:]
        if not (np.isfinite(inside).all() and np.isfinite(after).all()):
            continue
        half = 0.5 * (float(np.median(inside)) + float(np.median(after)))
        below = np.flatnonzero(row[n_in:] <= half)
        if not len(below):
            continue
        j = int(below[0]) + n_in
        a, b = float(row[j - 1]), float(row[j])
        frac = (a - half) / (a - b) if a > b else 0.5
        out[k] = sf[i, j - 1] + frac * SAMPLE_PX * step
    return out


@dataclass
class Lines:
    """One view's silhouette lines: world (x, y) of their far-outline points, the height each gives
    (its end / cot φ: the roof above the ground at that point, as the terrain-relative map drew
    it) and the tolerance within which a line agrees with a fit (m)."""

    xy: np.ndarray
    h: np.ndarray
    inlier: float


def silhouette_lines(fp: Footprint, grid, win, d: np.ndarray, d_px: np.ndarray, cot: float, u_max: float,
                     obl: tuple[np.ndarray, np.ndarray], obl_off: np.ndarray, nad: tuple[np.ndarray, np.ndarray],
                     nad_off: np.ndarray, settings: MatchSettings,
                     neighbours: Sequence[Footprint] = ()) -> Lines | str:
    """The lines of ``fp`` on one oblique view (``grid``/``win``: the nadir grid and the footprint's
    window in it), or why there are too few. Lines that run onto a ``neighbours`` footprint within
    NEIGHBOUR_M are left out: beyond a shared wall the nadir map shows the neighbour's roof, which
    its own move on the oblique map may match, ending the line early."""
    d = np.asarray(d, np.float64)
    pts = far_outline(fp, d, LINE_PX * grid.res)
    for o in neighbours:
        for t in np.arange(0.25, NEIGHBOUR_M + 1e-9, 0.5):
            pts = pts[~contains(o, pts[:, 0] + t * d[0], pts[:, 1] + t * d[1])]
    if len(pts) < MIN_LINES:
        return "silhouette_small"
    cols, rows = grid.colrow(pts[:, 0], pts[:, 1])
    start = np.stack([rows - 0.5 - win.row0, cols - 0.5 - win.col0])
    o_rgb, o_a = obl
    n_rgb, n_a = nad
    ends = line_ends(start, d_px, u_max, (_smooth(o_rgb), o_a), obl_off, (_smooth(n_rgb), n_a), nad_off,
                     settings.tol)
    ok = np.isfinite(ends)
    if np.count_nonzero(ok) < max(MIN_LINES, 0.3 * len(ends)):
        return "silhouette_lines"
    px_m = 1.0 / float(np.hypot(*d_px)) / cot         # metres of height per pixel of move
    return Lines(pts[ok], ends[ok] / cot, max(INLIER_PX * px_m, 0.25))


def outline_ground(fp: Footprint, xy: np.ndarray, sample: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> np.ndarray:
    """The ground a terrain-relative map subtracted at outline points ``xy`` (n, 2): the renderer
    takes the DTM at each vertex, so along an outline edge it is ``sample`` at the edge's two
    corners, linearly interpolated (each point on its nearest edge)."""
    ring = fp.rings[0]
    a, b = ring, np.roll(ring, -1, axis=0)
    za, zb = sample(a[:, 0], a[:, 1]), sample(b[:, 0], b[:, 1])
    e = b - a
    ee = np.maximum(np.einsum("ij,ij->i", e, e), 1e-12)
    t = np.clip(np.einsum("kij,ij->ki", xy[:, None, :] - a[None], e) / ee, 0.0, 1.0)
    gap = np.linalg.norm(xy[:, None, :] - (a[None] + t[..., None] * e[None]), axis=-1)
    k = np.argmin(gap, axis=1)
    tk = t[np.arange(len(xy)), k]
    return (1.0 - tk) * za[k] + tk * zb[k]


def levelled(fp: Footprint, lines: Lines, sample: Callable[[np.ndarray, np.ndarray], np.ndarray],
             base: float) -> Lines:
    """``lines`` with each height moved onto one basis: the roof z it gives (its height plus the
    ground the map subtracted there, :func:`outline_ground`) minus ``base`` (the mean ground under
    the footprint). On sloped ground every line of a flat roof then gives the same height, whichever
    edge it starts from (without the DTM a single view's lines show the slope along one edge only)."""
    return Lines(lines.xy, lines.h + outline_ground(fp, lines.xy, sample) - base, lines.inlier)


def roof_heights(fp: Footprint, lines: dict[str, Lines], slope: bool = True) -> dict[str, tuple[float, float, str]]:
    """Per view: (height at the footprint's area centroid, share of its lines on the fit, reason).

    ``slope``: one plane through the lines of every view (their far outlines differ, so together
    they show how the ground slopes under the roof), then each view's own level with that slope:
    the roof above the mean of a planar ground under the footprint, the basis a terrain-relative map
    encodes. Without ``slope`` the lines are already :func:`levelled` and each view's level is its
    height (a slope fitted to them would only follow the lines that occluders lengthen).
    """
    xy = np.concatenate([v.xy for v in lines.values()])
    gx = gy = 0.0
    centre = xy.mean(axis=0)
    cx, cy = centre
    if slope:
        fit = plane_fit(xy, np.concatenate([v.h for v in lines.values()]), max(v.inlier for v in lines.values()))
        if fit is None:
            return {p: (math.nan, 0.0, "silhouette_spread") for p in lines}
        (_, gx, gy), _ = fit
        cx, cy = area_centroid(fp.rings[0])
    out = {}
    for p, v in lines.items():
        own, share = robust_level(v.h - gx * (v.xy[:, 0] - centre[0]) - gy * (v.xy[:, 1] - centre[1]), v.inlier)
        if share < MIN_CONSISTENT:
            out[p] = (math.nan, share, "silhouette_spread")
        else:
            out[p] = (own + gx * (cx - centre[0]) + gy * (cy - centre[1]), share, "")
    return out


def robust_level(level: np.ndarray, inlier: float) -> tuple[float, float]:
    """(level, share of the values within ``inlier`` of it): the median, then three times the mean
    of the values within ``inlier``."""
    own = float(np.median(level))
    for _ in range(3):
        near = np.abs(level - own) <= inlier
        if not near.any():
            break
        own = float(np.mean(level[near]))
    return own, float(np.mean(np.abs(level - own) <= inlier))


def area_centroid(ring: np.ndarray) -> tuple[float, float]:
    """Area centroid (x, y) of a polygon ring (the vertices' mean if it has no area)."""
    x, y = ring[:, 0] - ring[0, 0], ring[:, 1] - ring[0, 1]
    cross = x * np.roll(y, -1) - np.roll(x, -1) * y
    a = cross.sum() / 2
    if abs(a) < 1e-12:
        return float(ring[:, 0].mean()), float(ring[:, 1].mean())
    return (float((x + np.roll(x, -1)) @ cross / (6 * a) + ring[0, 0]),
            float((y + np.roll(y, -1)) @ cross / (6 * a) + ring[0, 1]))


def plane_fit(xy: np.ndarray, h: np.ndarray, inlier: float, prior: float = 1.0,
              iterations: int = 6) -> tuple[tuple[float, float, float], float] | None:
    """Robust plane h ≈ h0 + gx·(x − x̄) + gy·(y − ȳ) through the line heights, (x̄, ȳ) their mean:
    least squares, then refitted on the points within 2.5 robust sigmas (at least ``inlier``);
    the slopes are pulled towards 0 with weight ``prior`` × n (a line of points along one edge
    leaves the slope across it unknown: the roof's height above a DTM that slopes under it
    varies along the edge, but nothing shows how it varies across). Returns ((h0, gx, gy), share of
    points within ``inlier`` of the plane), None without a fit."""
    q = xy - xy.mean(axis=0)
    a = np.column_stack([np.ones(len(h)), q])
    keep = np.ones(len(h), bool)
    coef = None
    for _ in range(iterations):
        n = int(np.count_nonzero(keep))
        if n < 3:
            return None
        reg = np.diag([0.0, prior * n, prior * n])
        ak = a[keep]
        coef = np.linalg.solve(ak.T @ ak + reg, ak.T @ h[keep])
        r = h - a @ coef
        sigma = max(1.4826 * float(np.median(np.abs(r[keep]))), inlier / 2.5)
        new = np.abs(r) <= 2.5 * sigma
        if (new == keep).all():
            break
        keep = new
    if coef is None:
        return None
    r = h - a @ coef
    return (float(coef[0]), float(coef[1]), float(coef[2])), float(np.mean(np.abs(r) <= inlier))
