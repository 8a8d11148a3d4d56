"""Building heights measured on the maps: how far each roof moved between the nadir and an oblique map.

On a north-up oblique map a point h metres above the DTM appears at its ground position
+ h·cot φ·d, d = (sin θ, cos θ) (see :mod:`pipeline25d.geometry.camera`); the nadir map shows it at
its ground position. A flat roof H metres high is therefore the nadir map's appearance of the
footprint, moved by H·cot φ along d. For each footprint and oblique map this module searches
that move u (metres along d, 0 ≤ u ≤ max_height·cot φ) and turns it into H = u / cot φ.

Matching (one footprint, one oblique map), all in nadir-grid pixels. Untextured models give
roofs of one uniform colour (often the same for every building), so a roof-only correlation is
degenerate; what pins a roof is where its colour *ends*:

* template: the nadir map's colours of the pixels whose centres lie inside the footprint;
  ring: pixels 2..ring_px+1 px outside it whose nadir colour differs from the nearest roof
  pixel's, which must *not* show that roof colour on the oblique map ("the roof ends where the
  footprint ends": no sliding inside a larger roof or onto the roof's own near-side wall); a
  ring pixel without data says nothing (left out of that move's score: beyond a model's edge
  a true roof borders no data, and beyond the map's a false one would);
* coarse scan at every pixel step of u: g(u) = 1 − mean truncated-quadratic colour loss
  (tolerance ``tol``; a pixel without data counts as a miss);
* peaks: a peak whose walls would hide ground that the oblique map shows unchanged from the
  nadir map in more than ``max_unchanged`` of the places tested is dropped; rival peaks (within
  ``max_second`` of the best, above the scan's median) are checked against that ground too:
  walls of a roof moved by u cover the area swept between footprint and roof, so a rival that
  sees clearly more of that area unchanged from the nadir map (``unchanged_margin``;
  roof-coloured places say nothing) is dropped. The best peak must
  match ≥ ``min_match`` of the template (else "hidden"), have no rival left ("ambiguous") and
  g must drop on both sides by ≥ ``min_drop`` × the share that a 2-px move uncovers ("flat":
  the roof could slide, e.g. along a row of same-coloured roofs);
* sub-pixel: (1) colour SSD over the template pixels matching near the peak (occluders and
  3 px around them left out), cubic splines, 0.1-px grid of u and a parabola; (2) around that,
  the anti-aliased edge pixels are compared through their nadir roof fraction a against
  a·(oblique colour 1.5 px inside) + (1 − a)·(oblique colour 1.5 px outside), so the roof's
  neighbour may differ between the maps (ground on the nadir map, the wall or another roof on
  the oblique map) without biasing u.

Per building: an ambiguous view is settled by the other views when exactly one of its rivals
agrees (``agree_m``) with their height; with three or more accepted views, a view more than
``outlier_m`` from the median of the others is rejected ("inconsistent": its roof was hidden
and a like roof further along the view matched), and two views that far apart are both
rejected (no majority says which matched); the accepted views are combined by their median and
``n_agree`` counts those within ``agree_m`` of it. Heights are relative to the ground that the
maps used (the DTM under the roof's outline).

CLI::

    python -m pipeline25d.analysis.heights MAPS_DIR --footprints FILE [--layer L] [--id-field F] \
        [--out heights.csv] [--reference ref.csv] [--json stats.json]
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import logging
import math
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from pipeline25d.analysis.evaluate import _open, _pair_grids, _same_crs
from pipeline25d.core.errors import CRSError, InputFileError, Pipeline25dError
from pipeline25d.core.raster import dataset_bounds, read_rgba_block
from pipeline25d.formats.footprints import Footprint, contains, rasterize, read_footprints
from pipeline25d.geometry.camera import horizontal_direction, relief_factor
from pipeline25d.geometry.perspectives import ID_PATTERN, Perspective

log = logging.getLogger(__name__)

NADIR_ID = "az000_el90"


# --------------------------------------------------------------------------- results

@dataclass(frozen=True)
class MatchSettings:
    """Matcher settings (see the module docstring). Colour distances are RGB, 0-255 per channel."""

    max_height: float = 200.0     # m; the search range is 0..max_height·cot φ along d
    ring_px: int = 2              # ring width outside the footprint (0: template only)
    min_pixels: int = 16          # smaller footprints (nadir pixels) are not measured
    tol: float = 30.0             # colour distance below which a pixel matches
    min_match: float = 0.5        # fraction of the template matching at the peak
    max_second: float = 0.75      # second peak / first peak (both above the scan's median)
    min_drop: float = 0.25        # g must fall by this × the 2-px uncovered fraction on both sides
    unchanged_margin: float = 0.2  # a rival peak is dropped when it sees this much more hidden ground unchanged
    max_unchanged: float = 0.8    # a peak whose walls would hide ground that is seen unchanged this often is dropped
    max_fine_px: int = 20000      # template pixels used for the sub-pixel fit (edge pixels always kept)
    agree_m: float = 0.5          # views within this of the combined height agree
    outlier_m: float = 2.0        # with 3+ accepted views, one this far from the others' median is rejected
    checked_peaks: int = 8        # the best peaks checked against the ground their walls would hide


@dataclass
class ViewMeasurement:
    """One footprint in one oblique map. ``height`` is NaN unless accepted (``reason`` == '')."""

    height: float
    shift_m: float                # roof move along d (m), NaN when no peak was found
    quality: float                # match fraction at the peak × (1 − second-peak ratio), 0..1
    match: float                  # fraction of the template matching at the peak
    second: float                 # second-peak ratio
    reason: str                   # '' (accepted) or why not
    resolved: bool = False        # ambiguous alone, settled by the other views


@dataclass
class HeightRow:
    """Per building: per-view heights (NaN = not measured), the combined height and its support."""

    id: str
    heights: dict[str, float]
    qualities: dict[str, float]
    reasons: dict[str, str]
    n_views: int                  # accepted views
    n_agree: int                  # accepted views within agree_m of the combined height
    height: float                 # median of the accepted views (NaN if none)
    quality: float                # median quality of accepted views × n_agree / n_views (0 if none)
    views: dict[str, ViewMeasurement] = field(default_factory=dict, repr=False)


# --------------------------------------------------------------------------- raster access

_PAD = 4


@dataclass
class _View:
    pid: str
    cot: float
    d_px: np.ndarray              # (row, col) nadir-grid pixels per metre of move along d
    src: Any                      # oblique dataset (or its resampling onto the nadir grid)
    offset: np.ndarray            # (row, col): src index = nadir index + offset + u·d_px


def _prepare_view(pid: str, path: str | Path, nad, nad_path: str | Path) -> _View:
    obl = _open(path)
    if not _same_crs(nad.GetProjection(), obl.GetProjection()):
        raise CRSError(f"{path} and {nad_path} are in different CRSs")
    p = Perspective.from_id(pid)
    gt = nad.GetGeoTransform()
    pair = _pair_grids(obl, nad, path)
    d = horizontal_direction(p)
    d_px = np.array([d[1] / gt[5], d[0] / gt[1]])
    offset = np.array([pair.obl_off[1] - pair.nad_off[1] - pair.frac[1],
                       pair.obl_off[0] - pair.nad_off[0] - pair.frac[0]], dtype=np.float64)
    return _View(pid, relief_factor(p), d_px, pair.src, offset)


# --------------------------------------------------------------------------- template

@dataclass
class Template:
    """A footprint's appearance on the nadir map, in the pixels of a nadir window.

    ``rows``/``cols``/``colour``: footprint pixels with data; ``ring_*``: ring pixels whose
    colour differs from the nearest roof pixel's, with that roof colour (``ring_roof``);
    edge model (per footprint pixel): ``edge`` marks mixed pixels within 1 px of a straight
    stretch of the outline, ``p_in``/``p_out`` (2, n) (row, col) are the points 1.5 px inside
    and outside that edge, ``cover`` the pixel's roof fraction on the nadir map; ``deep``
    marks pixels > 2.5 px inside. All coordinates are nadir-window indices (pixel centres).
    """

    mask: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    colour: np.ndarray
    ring_rows: np.ndarray
    ring_cols: np.ndarray
    ring_roof: np.ndarray
    edge: np.ndarray
    p_in: np.ndarray
    p_out: np.ndarray
    cover: np.ndarray
    deep: np.ndarray


def _sample(img: np.ndarray, rows: np.ndarray, cols: np.ndarray, order: int = 1) -> np.ndarray:
    """(n, 3) float64 colours of an (h, w, 3) image at float (row, col), spline ``order``, edges clamped."""
    from scipy import ndimage

    return np.stack([ndimage.map_coordinates(img[:, :, ch].astype(np.float64), [rows, cols], order=order,
                                             mode="nearest") for ch in range(img.shape[2])], axis=-1)


def build_template(fp: Footprint, geotransform: tuple[float, ...], col0: int, row0: int, nad_rgb: np.ndarray,
                   nad_alpha: np.ndarray, settings: MatchSettings) -> Template | str:
    """The matching template of ``fp`` from a nadir window at (col0, row0); a reason string if unusable."""
    from scipy import ndimage

    s, gt = settings, geotransform
    h, w = nad_alpha.shape
    mask = rasterize(fp, gt, col0, row0, w, h)
    tmpl = mask & (nad_alpha == 255)
    tr, tc = np.nonzero(tmpl)
    if len(tr) < s.min_pixels:
        return "too_small"
    if len(tr) < 0.5 * np.count_nonzero(mask):
        return "nadir_nodata"
    colour = nad_rgb[tr, tc].astype(np.float64)
    tol2 = s.tol ** 2

    # ring: pixels 2..ring_px+1 outside whose nadir colour differs from the nearest roof pixel's
    if s.ring_px > 0:
        ring = (ndimage.binary_dilation(mask, iterations=s.ring_px + 1) & ~ndimage.binary_dilation(mask)
                & (nad_alpha == 255))
        _, (ir, ic) = ndimage.distance_transform_edt(~mask, return_indices=True)
        rr, rc = np.nonzero(ring)
        roof = nad_rgb[ir[rr, rc], ic[rr, rc]].astype(np.float64)
        active = np.sum((nad_rgb[rr, rc] - roof) ** 2, axis=-1) > tol2
        rr, rc, roof = rr[active], rc[active], roof[active]
    else:
        rr = rc = np.zeros(0, np.int64)
        roof = np.zeros((0, 3))

    # edge model: nearest straight outline stretch of the pixels near the outline
    gsd = gt[1]
    x = gt[0] + (col0 + tc + 0.5) * gt[1]
    y = gt[3] + (row0 + tr + 0.5) * gt[5]
    depth = ndimage.distance_transform_edt(np.pad(mask, 1))[1:-1, 1:-1][tr, tc]
    near = np.flatnonzero(depth <= 3)
    seg_a = np.concatenate([r for r in fp.rings])
    seg_b = np.concatenate([np.roll(r, -1, axis=0) for r in fp.rings])
    e = seg_b - seg_a
    length = np.hypot(e[:, 0], e[:, 1])
    keep = length > 0
    seg_a, seg_b, e, length = seg_a[keep], seg_b[keep], e[keep], length[keep]
    normal = np.stack([e[:, 1], -e[:, 0]], axis=1) / length[:, None]
    mid = (seg_a + seg_b) / 2 + 1e-4 * gsd * normal
    normal[contains(fp, mid[:, 0], mid[:, 1])] *= -1                 # outward
    # vertices where the outline turns by more than 10°: pixels near them are not single-edge mixes
    turns = []
    for ring in fp.rings:
        ein, eout = ring - np.roll(ring, 1, axis=0), np.roll(ring, -1, axis=0) - ring
        cosang = np.sum(ein * eout, axis=1) / np.maximum(np.hypot(*ein.T) * np.hypot(*eout.T), 1e-300)
        turns.append(ring[cosang < math.cos(math.radians(10))])
    turns = np.concatenate(turns) if turns else np.zeros((0, 2))

    edge = np.zeros(len(tr), bool)
    deep = depth > 2.5
    p_in = np.zeros((2, len(tr)))
    p_out = np.zeros((2, len(tr)))
    cover = np.zeros(len(tr))
    if len(near) and len(seg_a):
        px, py = x[near, None], y[near, None]
        t = np.clip(((px - seg_a[:, 0]) * e[:, 0] + (py - seg_a[:, 1]) * e[:, 1]) / length ** 2, 0.0, 1.0)
        dist = np.hypot(px - seg_a[:, 0] - t * e[:, 0], py - seg_a[:, 1] - t * e[:, 1])
        j = np.argmin(dist, axis=1)
        delta = dist[np.arange(len(near)), j]
        nrm = normal[j]
        ok = delta <= gsd
        if len(turns):
            dv = np.hypot(x[near, None] - turns[:, 0], y[near, None] - turns[:, 1]).min(axis=1)
            ok &= dv >= 2.0 * gsd
        xin, yin = x[near] - nrm[:, 0] * (1.5 * gsd - delta), y[near] - nrm[:, 1] * (1.5 * gsd - delta)
        xout, yout = x[near] + nrm[:, 0] * (1.5 * gsd + delta), y[near] + nrm[:, 1] * (1.5 * gsd + delta)
        ok &= contains(fp, xin, yin) & ~contains(fp, xout, yout)
        to_idx = lambda xx, yy: np.stack([(yy - gt[3]) / gt[5] - 0.5 - row0,  # noqa: E731
                                          (xx - gt[0]) / gt[1] - 0.5 - col0])
        pin, pout = to_idx(xin, yin), to_idx(xout, yout)
        r_n, x_n = _sample(nad_rgb, *pin), _sample(nad_rgb, *pout)
        contrast2 = np.sum((r_n - x_n) ** 2, axis=1)
        ok &= contrast2 > tol2
        a = np.clip(np.sum((colour[near] - x_n) * (r_n - x_n), axis=1) / np.maximum(contrast2, 1e-9), 0.0, 1.0)
        sel = near[ok]
        edge[sel] = True
        p_in[:, sel], p_out[:, sel], cover[sel] = pin[:, ok], pout[:, ok], a[ok]
    return Template(mask, tr, tc, colour, rr, rc, roof, edge, p_in, p_out, cover, deep)


# --------------------------------------------------------------------------- matching

def _uncovered(mask: np.ndarray, step: np.ndarray) -> float:
    """Fraction of ``mask`` pixels whose (row, col) + step (rounded) falls outside the mask."""
    rr, cc = np.nonzero(mask)
    r2, c2 = np.round(rr + step[0]).astype(int), np.round(cc + step[1]).astype(int)
    inside = (r2 >= 0) & (r2 < mask.shape[0]) & (c2 >= 0) & (c2 < mask.shape[1])
    hit = np.zeros(len(rr), bool)
    hit[inside] = mask[r2[inside], c2[inside]]
    return float(1.0 - hit.mean()) if len(rr) else 0.0


def _gather(rgb: np.ndarray, alpha: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-pixel colours (…, 3) and validity (…) at float positions; outside: invalid."""
    r, c = np.rint(rows).astype(np.int64), np.rint(cols).astype(np.int64)
    h, w = alpha.shape
    ok = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    r, c = np.where(ok, r, 0), np.where(ok, c, 0)
    ok &= alpha[r, c] == 255
    return rgb[r, c], ok


def _unchanged(t: Template, sweep: tuple[np.ndarray, np.ndarray, np.ndarray], obl_rgb: np.ndarray,
               obl_alpha: np.ndarray, offset: np.ndarray, d_px: np.ndarray, u: float, tol2: float,
               n: int = 2000) -> float:
    """Share of what a roof moved by u would hide (the swept area off the footprint and off the
    moved roof) that the oblique map shows as the nadir map does. Places whose nadir colour
    is like the roof's (e.g. neighbouring roofs) say nothing and are left out; 0 when fewer
    than 20 places are left."""
    nad_rgb, nad_alpha, sw_off = sweep
    if u <= 0:
        return 0.0
    rng = np.random.default_rng(1)
    i = rng.integers(0, len(t.rows), n)
    tt = rng.uniform(0.0, u, n)
    lr, lc = t.rows[i] + tt * d_px[0], t.cols[i] + tt * d_px[1]
    h, w = t.mask.shape

    def in_mask(r: np.ndarray, c: np.ndarray) -> np.ndarray:
        ri, ci = np.rint(r).astype(np.int64), np.rint(c).astype(np.int64)
        ok = (ri >= 0) & (ri < h) & (ci >= 0) & (ci < w)
        out = np.zeros(len(r), bool)
        out[ok] = t.mask[ri[ok], ci[ok]]
        return out

    keep = np.ones(n, bool)
    for dr, dc in ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)):   # a pixel off the outlines (mixed pixels)
        keep &= ~in_mask(lr + dr, lc + dc) & ~in_mask(lr - u * d_px[0] + dr, lc - u * d_px[1] + dc)
    if np.count_nonzero(keep) < 20:
        return 0.0
    lr, lc = lr[keep], lc[keep]
    a, ok_a = _gather(nad_rgb, nad_alpha, lr + sw_off[0], lc + sw_off[1])
    b, ok_b = _gather(obl_rgb, obl_alpha, lr + offset[0], lc + offset[1])
    palette = t.colour[rng.integers(0, len(t.rows), 64)].astype(np.float32)
    roof_like = (np.sum((a[:, None, :] - palette[None]) ** 2, axis=-1) < tol2).any(axis=1)
    ok = ok_a & ok_b & ~roof_like
    if np.count_nonzero(ok) < 20:
        return 0.0
    return float(np.mean(np.sum((a[ok] - b[ok]) ** 2, axis=-1) < tol2))


@dataclass
class MatchResult:
    """One footprint in one oblique map: move u (m along d), match fraction, second-peak ratio,
    reason ('' = accepted) and, when ambiguous, the coarse moves of the rival peaks (best first)."""

    u: float
    match: float
    second: float
    reason: str
    rivals: list[float] = field(default_factory=list)


class _Matcher:
    """Coarse scan of one footprint over one oblique window; :meth:`result` picks and refines a peak.

    An oblique window index is the nadir window index + ``offset`` + u·``d_px`` (row, col).
    ``sweep``: (rgb, alpha, sweep_offset) of the nadir map over the area the search sweeps
    (index = nadir window index + sweep_offset), for the hidden-ground check.
    """

    def __init__(self, t: Template, obl_rgb: np.ndarray, obl_alpha: np.ndarray, offset: np.ndarray,
                 d_px: np.ndarray, u_max: float, step_m: float, settings: MatchSettings,
                 sweep: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None):
        from scipy.signal import find_peaks

        self.t, self.obl_rgb, self.obl_alpha, self.offset, self.d_px = t, obl_rgb, obl_alpha, offset, d_px
        self.step_m, self.s = step_m, settings
        s = settings
        tol2 = self.tol2 = s.tol ** 2
        n_t, n_r = len(t.rows), len(t.ring_rows)
        # coarse scan: every step_m of u, nearest pixels, robust score g(u) in [0, 1]
        us = self.us = np.arange(-3, int(math.floor(u_max / step_m)) + 4) * step_m
        g = self.g = np.empty(len(us))
        self.base_t = base_t = np.stack([t.rows + offset[0], t.cols + offset[1]])
        base_r = np.stack([t.ring_rows + offset[0], t.ring_cols + offset[1]])
        self.tcol = tcol = t.colour.astype(np.float32)
        rcol = t.ring_roof.astype(np.float32)
        chunk = max(1, 2_000_000 // (n_t + n_r))
        for i in range(0, len(us), chunk):
            u = us[i:i + chunk, None]
            col, ok = _gather(obl_rgb, obl_alpha, base_t[0] + u * d_px[0], base_t[1] + u * d_px[1])
            loss = np.where(ok, np.minimum(np.sum((col - tcol) ** 2, axis=-1), tol2) / tol2, 1.0).sum(axis=1)
            n = np.full(len(u), float(n_t))
            if n_r:
                col, ok = _gather(obl_rgb, obl_alpha, base_r[0] + u * d_px[0], base_r[1] + u * d_px[1])
                e2 = np.sum((col - rcol) ** 2, axis=-1)
                loss += np.where(ok, 1.0 - np.minimum(e2, tol2) / tol2, 0.0).sum(axis=1)
                n += ok.sum(axis=1)
            g[i:i + chunk] = 1.0 - loss / n

        # peaks (the scan's ends count), best first, one per 2 steps
        in_range = (us >= -step_m) & (us <= u_max + 1e-9)
        self.floor = float(np.median(g[in_range]))
        peaks, props = find_peaks(np.concatenate([[-1.0], np.where(in_range, g, -1.0), [-1.0]]), prominence=0.0)
        peaks -= 1
        order = np.argsort(g[peaks])[::-1]
        min_prom = 0.1 * max(float(g[peaks[order[0]]]) - self.floor, 1e-6) if len(peaks) else 0.0
        cands: list[int] = []
        for i, j in enumerate(order):
            k = int(peaks[j])
            if (i == 0 or props["prominences"][j] >= min_prom) and all(abs(k - c) > 2 for c in cands):
                cands.append(k)
        # rivals (peaks nearly as good as the best): a peak at u says the walls hide what lies between
        # the footprint and the moved roof; a rival that sees clearly more of it unchanged than
        # another is contradicted and dropped
        seen: dict[int, float] = {}

        def unchanged(k: int) -> float:
            if k not in seen:
                seen[k] = _unchanged(t, sweep, obl_rgb, obl_alpha, offset, d_px, float(us[k]), tol2)
            return seen[k]

        if sweep is not None:
            # a peak whose walls would hide ground that the oblique map shows as the nadir map does is
            # contradicted, whatever its rivals (e.g. a roof slid onto a like roof far along the view)
            cands = [k for i, k in enumerate(cands) if i >= s.checked_peaks or unchanged(k) <= s.max_unchanged]
        rivals = [k for k in cands[:s.checked_peaks] if self._rel(k, cands) > s.max_second]
        if len(rivals) > 1 and sweep is not None:
            lowest = min(unchanged(k) for k in rivals)   # a rival moved up into the first few is measured now
            cands = [k for k in cands if seen.get(k, lowest) <= lowest + s.unchanged_margin]
        self.cands = cands

    def _rel(self, k: int, cands: list[int]) -> float:
        return (float(self.g[k]) - self.floor) / max(float(self.g[cands[0]]) - self.floor, 1e-9)

    def result(self, window: tuple[float, float] | None = None) -> MatchResult:
        """The best peak (within ``window`` = (u_lo, u_hi) if given), checked and refined."""
        from scipy import ndimage

        s, t, g, us, d_px, tol2 = self.s, self.t, self.g, self.us, self.d_px, self.tol2
        cands = [k for k in self.cands if window is None or window[0] <= us[k] <= window[1]]
        if not cands:
            return MatchResult(math.nan, 0.0, 1.0, "no_peak")
        k0, g1 = cands[0], float(g[cands[0]])
        g2 = float(g[cands[1]]) if len(cands) > 1 else self.floor
        second = float(np.clip((g2 - self.floor) / max(g1 - self.floor, 1e-9), 0.0, 1.0))
        u0 = float(us[k0])
        col, ok = self._at(u0)
        match = float(np.mean(ok & (np.sum((col - self.tcol) ** 2, axis=-1) < tol2)))
        if match < s.min_match:
            return MatchResult(u0, match, second, "hidden")
        if second > s.max_second:
            rivals = [float(us[k]) for k in cands[:8] if self._rel(k, cands) > s.max_second]
            return MatchResult(u0, match, second, "ambiguous", rivals)
        # the roof must not slide: g falls on both sides by a share of what a 2-px move uncovers
        scale = max(abs(d_px[0]), abs(d_px[1]))
        k2 = max(1, int(round(2.0 / (self.step_m * scale))))
        expect = _uncovered(t.mask, 2.0 * d_px / scale) * match
        for kk in (k0 - k2, k0 + k2):
            if 0 <= kk < len(g) and g1 - g[kk] < s.min_drop * expect:
                return MatchResult(u0, match, second, "flat")

        # inliers: template pixels matching within one step of the peak, away from occluders
        # (pixels > 2 px inside that match nowhere there, grown by 3 px)
        n_t = len(t.rows)
        inl = np.zeros(n_t, bool)
        for du in (-self.step_m, 0.0, self.step_m):
            col, ok = self._at(u0 + du)
            inl |= ok & (np.sum((col - self.tcol) ** 2, axis=-1) < tol2)
        interior = ndimage.binary_erosion(t.mask, iterations=2, border_value=0)[t.rows, t.cols]
        missed = np.zeros(t.mask.shape, bool)
        missed[t.rows[~inl & interior], t.cols[~inl & interior]] = True
        if missed.any():
            inl &= ~ndimage.binary_dilation(missed, iterations=3)[t.rows, t.cols]
        if np.count_nonzero(inl) < s.min_pixels:
            return MatchResult(u0, match, second, "unstable")
        if np.count_nonzero(inl) > s.max_fine_px:
            keep = inl & t.edge
            rest = np.flatnonzero(inl & ~t.edge)
            n_more = max(0, s.max_fine_px - int(np.count_nonzero(keep)))
            keep[np.random.default_rng(0).choice(rest, size=min(n_more, len(rest)), replace=False)] = True
            inl = keep
        u = self._refine(np.flatnonzero(inl), u0)
        if not np.isfinite(u):
            return MatchResult(u0, match, second, "unstable")
        return MatchResult(u, match, second, "")

    def _at(self, u: float) -> tuple[np.ndarray, np.ndarray]:
        b = self.base_t
        return _gather(self.obl_rgb, self.obl_alpha, b[0] + u * self.d_px[0], b[1] + u * self.d_px[1])

    def _refine(self, pix: np.ndarray, u0: float) -> float:
        """Sub-pixel u near the coarse peak u0 from the template pixels ``pix``; NaN if unstable."""
        t, d_px, step, base_t, off = self.t, self.d_px, self.step_m, self.base_t, self.offset
        sub, corner = _spline_window(self.obl_rgb, base_t[:, pix], d_px, u0 - 2 * step, u0 + 2 * step)
        if sub is None:
            return math.nan

        # 1: SSD of colours (robust, but biased where the roof's neighbour differs between the maps)
        def ssd(u: np.ndarray) -> np.ndarray:
            pred = _spline_at(sub, corner, base_t[:, pix], d_px, u)
            return np.sum((pred - t.colour[pix][None]) ** 2, axis=(1, 2))

        u1 = _grid_min(ssd, u0, 1.5 * step, 0.1 * step)
        if not np.isfinite(u1):
            return math.nan
        # 2: mixed edge pixels compared through their roof fraction with the oblique map's own
        # neighbour colour (wall, other ground); deep pixels by colour; near u1 only
        e_pix = pix[t.edge[pix]]
        d_pix = pix[t.deep[pix] & ~t.edge[pix]]
        if len(e_pix) < 4:
            return u1
        base_in = np.stack([t.p_in[0, e_pix] + off[0], t.p_in[1, e_pix] + off[1]])
        base_out = np.stack([t.p_out[0, e_pix] + off[0], t.p_out[1, e_pix] + off[1]])
        a = t.cover[e_pix][None, :, None]

        def model(u: np.ndarray) -> np.ndarray:
            o = _spline_at(sub, corner, base_t[:, e_pix], d_px, u)
            o_in = _spline_at(sub, corner, base_in, d_px, u)
            o_out = _spline_at(sub, corner, base_out, d_px, u)
            cost = np.sum((o - a * o_in - (1 - a) * o_out) ** 2, axis=(1, 2))
            if len(d_pix):
                o = _spline_at(sub, corner, base_t[:, d_pix], d_px, u)
                cost += np.sum((o - t.colour[d_pix][None]) ** 2, axis=(1, 2))
            return cost

        u2 = _grid_min(model, u1, 0.6 * step, 0.05 * step)
        return u2 if np.isfinite(u2) else u1


def match_footprint(t: Template, obl_rgb: np.ndarray, obl_alpha: np.ndarray, offset: np.ndarray,
                    d_px: np.ndarray, u_max: float, step_m: float, settings: MatchSettings,
                    sweep: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> MatchResult:
    """Move u (m along d, 0..u_max) of a footprint's roof from the nadir map to an oblique window.

    An oblique window index is the nadir window index + ``offset`` + u·``d_px`` (row, col);
    ``sweep`` (optional): the nadir map over the searched area, (rgb, alpha, index offset
    from the nadir window), used to drop rival peaks whose walls would hide visible ground.
    """
    return _Matcher(t, obl_rgb, obl_alpha, offset, d_px, u_max, step_m, settings, sweep).result()


def _spline_window(img: np.ndarray, base: np.ndarray, d_px: np.ndarray, u_lo: float,
                   u_hi: float) -> tuple[np.ndarray | None, np.ndarray]:
    """Cubic spline coefficients (h, w, 3) of the part of ``img`` that ``base`` + u·d_px (u_lo..u_hi) reaches."""
    from scipy import ndimage

    pts = np.concatenate([base + u * d_px[:, None] for u in (u_lo, u_hi)], axis=1)
    r0, c0 = int(math.floor(pts[0].min())) - 2 * _PAD, int(math.floor(pts[1].min())) - 2 * _PAD
    r1, c1 = int(math.ceil(pts[0].max())) + 2 * _PAD + 1, int(math.ceil(pts[1].max())) + 2 * _PAD + 1
    h, w = img.shape[:2]
    r0, c0, r1, c1 = max(r0, 0), max(c0, 0), min(r1, h), min(c1, w)
    if r1 - r0 < 4 or c1 - c0 < 4:
        return None, np.zeros(2)
    win = img[r0:r1, c0:c1].astype(np.float64)
    coef = np.stack([ndimage.spline_filter(win[:, :, ch], order=3, mode="nearest") for ch in range(3)], axis=-1)
    return coef, np.array([r0, c0], dtype=np.float64)


def _spline_at(coef: np.ndarray, corner: np.ndarray, base: np.ndarray, d_px: np.ndarray,
               u: np.ndarray) -> np.ndarray:
    """(len(u), n, 3) colours at ``base`` (2, n) + u·d_px from spline coefficients."""
    from scipy import ndimage

    u = np.atleast_1d(u)
    rows = (base[0][None, :] + u[:, None] * d_px[0] - corner[0]).ravel()
    cols = (base[1][None, :] + u[:, None] * d_px[1] - corner[1]).ravel()
    out = np.stack([ndimage.map_coordinates(coef[:, :, ch], [rows, cols], order=3, mode="nearest",
                                            prefilter=False) for ch in range(3)], axis=-1)
    return out.reshape(len(u), base.shape[1], 3)


def _grid_min(cost_fn, centre: float, half: float, step: float) -> float:
    """Minimum of cost_fn on centre ± half (grid ``step``) refined by a parabola; NaN at the grid's ends."""
    n = int(round(half / step))
    us = centre + np.arange(-n, n + 1) * step
    cost = cost_fn(us)
    k = int(np.argmin(cost))
    if k == 0 or k == len(cost) - 1:
        return math.nan
    a, b, c = cost[k - 1], cost[k], cost[k + 1]
    den = a - 2 * b + c
    return float(us[k] + (0.5 * (a - c) / den * step if den > 0 else 0.0))


# --------------------------------------------------------------------------- main entry

def measure_heights(map_paths: dict[str, str | Path], footprints: list[Footprint], nadir_id: str = NADIR_ID,
                    settings: MatchSettings | None = None) -> list[HeightRow]:
    """Height of every footprint in every oblique map of ``map_paths`` ({perspective id: GeoTIFF}).

    The maps must share the nadir map's CRS (CRSError naming them otherwise); footprints are
    in that CRS. A view left ambiguous (rival peaks) is settled by the others when exactly one
    of its rivals lies within ``agree_m`` of the height they give (the accepted views' median,
    or else the one height that rivals of two or more views share); such a view is marked
    ``resolved``. Returns one row per footprint, in input order.
    """
    s = settings or MatchSettings()
    if nadir_id not in map_paths:
        raise InputFileError(nadir_id, f"no nadir map {nadir_id!r} among {sorted(map_paths)}")
    nad_path = map_paths[nadir_id]
    nad = _open(nad_path)
    gt = nad.GetGeoTransform()
    if abs(gt[1] + gt[5]) > 1e-9 * gt[1]:
        raise InputFileError(nad_path, f"pixels must be square, geotransform {gt}")
    views = [_prepare_view(pid, path, nad, nad_path) for pid, path in sorted(map_paths.items())
             if pid != nadir_id and Perspective.from_id(pid).elevation != 90]
    step_m = gt[1]
    pad = s.ring_px + 4
    rows_out: list[HeightRow] = []
    for fp in footprints:
        xmin, ymin, xmax, ymax = fp.bounds
        c0 = int(math.floor((xmin - gt[0]) / gt[1])) - pad
        c1 = int(math.ceil((xmax - gt[0]) / gt[1])) + pad
        r0 = int(math.floor((ymax - gt[3]) / gt[5])) - pad
        r1 = int(math.ceil((ymin - gt[3]) / gt[5])) + pad
        if c1 <= 0 or r1 <= 0 or c0 >= nad.RasterXSize or r0 >= nad.RasterYSize:
            tmpl: Template | str = "outside_nadir"
        else:
            nad_rgb, nad_alpha = read_rgba_block(nad, c0, r0, c1 - c0, r1 - r0)
            tmpl = build_template(fp, gt, c0, r0, nad_rgb, nad_alpha, s)
        results: dict[str, MatchResult] = {}
        matchers: dict[str, _Matcher] = {}
        for v in views:
            if isinstance(tmpl, str):
                results[v.pid] = MatchResult(math.nan, 0.0, 1.0, tmpl)
                continue
            u_max = s.max_height * v.cot
            # oblique window covering the nadir window moved by -3 .. u_max + 3 steps, clipped to the raster
            corners = np.array([[r0, c0], [r0, c1], [r1, c0], [r1, c1]], dtype=np.float64)
            pts = np.concatenate([corners + v.offset + u * v.d_px for u in (-3 * step_m, u_max + 3 * step_m)])
            o_r0 = max(int(math.floor(pts[:, 0].min())) - _PAD, -_PAD)
            o_c0 = max(int(math.floor(pts[:, 1].min())) - _PAD, -_PAD)
            o_r1 = min(int(math.ceil(pts[:, 0].max())) + _PAD, v.src.RasterYSize + _PAD)
            o_c1 = min(int(math.ceil(pts[:, 1].max())) + _PAD, v.src.RasterXSize + _PAD)
            if o_r1 <= o_r0 or o_c1 <= o_c0:
                results[v.pid] = MatchResult(math.nan, 0.0, 1.0, "outside_map")
                continue
            obl_rgb, obl_alpha = read_rgba_block(v.src, o_c0, o_r0, o_c1 - o_c0, o_r1 - o_r0)
            off = v.offset + np.array([r0 - o_r0, c0 - o_c0], dtype=np.float64)
            # the nadir map over the same area (for the hidden-ground check)
            n_r0, n_c0 = o_r0 - int(round(v.offset[0])), o_c0 - int(round(v.offset[1]))
            sw_rgb, sw_alpha = read_rgba_block(nad, n_c0, n_r0, o_c1 - o_c0, o_r1 - o_r0)
            sweep = (sw_rgb, sw_alpha, np.array([r0 - n_r0, c0 - n_c0], dtype=np.float64))
            matchers[v.pid] = _Matcher(tmpl, obl_rgb, obl_alpha, off, v.d_px, u_max, step_m, s, sweep)
            results[v.pid] = matchers[v.pid].result()
        cot = {v.pid: v.cot for v in views}
        resolved = _resolve(results, matchers, cot, s.agree_m + step_m / max(min(cot.values(), default=1.0), 1e-9))
        measurements = {}
        for pid, r in results.items():
            reason = r.reason
            if not reason and not (-step_m <= r.u <= s.max_height * cot[pid] + step_m):
                reason = "out_of_range"
            h = r.u / cot[pid] if not reason else math.nan
            measurements[pid] = ViewMeasurement(h, r.u, r.match * (1.0 - r.second), r.match, r.second, reason,
                                                pid in resolved)
        _drop_inconsistent(measurements, s.outlier_m)
        rows_out.append(_combine(fp.id, measurements, s))
    return rows_out


def _resolve(results: dict[str, MatchResult], matchers: dict[str, "_Matcher"], cot: dict[str, float],
             tol_h: float) -> set[str]:
    """Settle ambiguous views by the height the others give (in place); returns the settled views."""
    amb = [p for p, r in results.items() if r.reason == "ambiguous" and p in matchers]
    if not amb:
        return set()
    accepted = [r.u / cot[p] for p, r in results.items() if not r.reason]
    rivals = {p: [u / cot[p] for u in results[p].rivals] for p in amb}
    if accepted:
        target = float(np.median(accepted))
    else:
        # heights that rivals of two or more views share; usable only if they are all one height
        shared = [(h1 + h2) / 2 for i, p in enumerate(amb) for q in amb[i + 1:]
                  for h1 in rivals[p] for h2 in rivals[q] if abs(h1 - h2) <= tol_h]
        if not shared or max(shared) - min(shared) > tol_h:
            return set()
        target = float(np.mean(shared))
    done = set()
    for p in amb:
        near = [h for h in rivals[p] if abs(h - target) <= tol_h]
        if len(near) != 1:
            continue
        r = matchers[p].result(window=((target - tol_h) * cot[p], (target + tol_h) * cot[p]))
        if not r.reason and abs(r.u / cot[p] - target) <= tol_h:
            results[p] = r
            done.add(p)
    return done


def _drop_inconsistent(views: dict[str, ViewMeasurement], outlier_m: float) -> None:
    """With three or more accepted views, reject (in place, reason "inconsistent") each view whose
    height lies more than ``outlier_m`` from the median of the other accepted views: a roof one
    view alone puts elsewhere (its own roof hidden there, a like roof further along the view).
    Two accepted views that differ by more than ``outlier_m`` are both rejected: with no third
    view there is no telling which one matched a like roof."""
    acc = {p: m.height for p, m in views.items() if not m.reason}
    far: list[str] = []
    if len(acc) == 2 and abs(np.subtract(*acc.values())) > outlier_m:
        far = list(acc)
    elif len(acc) >= 3:
        far = [p for p, h in acc.items() if abs(h - float(np.median([o for q, o in acc.items() if q != p]))) > outlier_m]
    for p in far:
        views[p] = replace(views[p], height=math.nan, reason="inconsistent")


def _combine(fid: str, views: dict[str, ViewMeasurement], s: MatchSettings) -> HeightRow:
    accepted = [m for m in views.values() if not m.reason]
    if accepted:
        hs = np.array([m.height for m in accepted])
        height = float(np.median(hs))
        n_agree = int(np.count_nonzero(np.abs(hs - height) <= s.agree_m))
        quality = float(np.median([m.quality for m in accepted])) * n_agree / len(accepted)
    else:
        height, n_agree, quality = math.nan, 0, 0.0
    return HeightRow(fid, {k: m.height for k, m in views.items()}, {k: m.quality for k, m in views.items()},
                     {k: m.reason for k, m in views.items()}, len(accepted), n_agree, height, quality, views)


# --------------------------------------------------------------------------- reference and comparison

def reference_heights_from_obj(path: str | Path, roof_material: str = "Building",
                               wall_material: str = "BuildingWall", ground: str = "terrain") -> dict[str, float]:
    """Building heights from an OBJ with per-class materials (e.g. a 3dfier export), float64:
    roof − ground of :func:`obj_roof_ground` per ``o`` object."""
    return {k: roof - g for k, (roof, g) in obj_roof_ground(path, roof_material, wall_material, ground).items()}


def obj_roof_ground(path: str | Path, roof_material: str = "Building", wall_material: str = "BuildingWall",
                    ground: str = "terrain") -> dict[str, tuple[float, float]]:
    """(roof z, ground z) per ``o`` object of an OBJ with per-class materials (e.g. a 3dfier export).

    Roof = area-weighted mean z of its ``roof_material`` faces; ground = ``"terrain"``: mean z
    of its wall vertices that faces of other classes (terrain, roads) share, i.e. where the
    walls meet the model's ground (the lowest wall z where none does), or ``"lowest"``: the
    lowest z of its walls. Objects without roof and walls are left out.
    """
    if ground not in ("terrain", "lowest"):
        raise ValueError(f"ground must be 'terrain' or 'lowest', not {ground!r}")
    path = Path(path)
    if not path.exists():
        raise InputFileError(path, "no such file")
    verts: list[tuple[float, float, float]] = []
    roof_sum: dict[str, list[float]] = {}
    walls: dict[str, set[int]] = {}
    others: set[int] = set()
    obj, mtl = "", ""
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            if line.startswith("v "):
                p = line.split()
                verts.append((float(p[1]), float(p[2]), float(p[3])))
            elif line.startswith("o "):
                obj = line[2:].strip()
            elif line.startswith("usemtl"):
                mtl = line[6:].strip()
            elif line.startswith("f "):
                try:
                    idx = [int(tok.split("/")[0]) for tok in line.split()[1:]]
                    idx = [i - 1 if i > 0 else len(verts) + i for i in idx]
                    pts = np.array([verts[i] for i in idx], dtype=np.float64)
                except (ValueError, IndexError):
                    raise InputFileError(path, f"line {lineno}: bad face {line.strip()!r}") from None
                if mtl == wall_material:
                    walls.setdefault(obj, set()).update(idx)
                elif mtl == roof_material:
                    acc = roof_sum.setdefault(obj, [0.0, 0.0])
                    for k in range(1, len(pts) - 1):
                        tri = pts[[0, k, k + 1]]
                        area = 0.5 * float(np.linalg.norm(np.cross(tri[1] - tri[0], tri[2] - tri[0])))
                        acc[0] += area * float(tri[:, 2].mean())
                        acc[1] += area
                elif not mtl.startswith(roof_material):
                    others.update(idx)
    z = np.array([v[2] for v in verts], dtype=np.float64)
    out: dict[str, tuple[float, float]] = {}
    for o, acc in roof_sum.items():
        if acc[1] <= 0 or o not in walls:
            continue
        wall = np.fromiter(walls[o], dtype=np.int64)
        foot = np.fromiter(walls[o] & others, dtype=np.int64) if ground == "terrain" else np.zeros(0, np.int64)
        out[o] = (acc[0] / acc[1], float(z[foot].mean()) if len(foot) else float(z[wall].min()))
    return out


def read_reference(path: str | Path) -> dict[str, float]:
    """{id: height} from a CSV with columns ``id`` and ``height``."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputFileError(path, f"cannot read: {exc.strerror or exc}") from None
    reader = csv.DictReader(io.StringIO(text))
    if not reader.fieldnames or "id" not in reader.fieldnames or "height" not in reader.fieldnames:
        raise InputFileError(path, f"needs columns 'id' and 'height', has {reader.fieldnames}")
    out = {}
    for n, row in enumerate(reader, 2):
        try:
            out[row["id"]] = float(row["height"])
        except (TypeError, ValueError):
            raise InputFileError(path, f"line {n}: height {row.get('height')!r} is not a number") from None
    return out


def error_stats(measured: np.ndarray, reference: np.ndarray) -> dict[str, float | int | None]:
    """n, bias (mean measured − reference), rmsd, median/p90 |error|, fraction within 0.5 m."""
    err = np.asarray(measured, float) - np.asarray(reference, float)
    err = err[np.isfinite(err)]
    if not len(err):
        return {"n": 0, "bias": None, "rmsd": None, "median_abs": None, "p90_abs": None, "within_0.5m": None}
    a = np.abs(err)
    return {"n": int(len(err)), "bias": round(float(err.mean()), 4),
            "rmsd": round(float(np.sqrt(np.mean(err ** 2))), 4),
            "median_abs": round(float(np.median(a)), 4), "p90_abs": round(float(np.percentile(a, 90)), 4),
            "within_0.5m": round(float(np.mean(a <= 0.5)), 4)}


def compare(rows: list[HeightRow], reference: dict[str, float]) -> dict[str, Any]:
    """Error statistics against ``reference`` heights: combined and per view."""
    by_id = {r.id: r for r in rows}
    common = [i for i in reference if i in by_id]
    ref = np.array([reference[i] for i in common])
    out: dict[str, Any] = {"n_reference": len(reference), "n_footprints_with_reference": len(common),
                           "combined": error_stats(np.array([by_id[i].height for i in common]), ref)}
    views = sorted({k for r in rows for k in r.heights})
    for v in views:
        out[v] = error_stats(np.array([by_id[i].heights.get(v, math.nan) for i in common]), ref)
    return out


def write_csv(path: str | Path, rows: list[HeightRow], extra: dict[str, dict[str, str]] | None = None) -> None:
    """One line per building: id, height, n_views, n_agree, quality, the ``extra`` columns
    ({column: {id: text}}, e.g. a reference), then per view height, quality, reason ('' =
    accepted) and resolved (1 = settled by the other views); unmeasured heights empty."""
    from pipeline25d.core.atomic import write_text

    extra = extra or {}
    views = sorted({k for r in rows for k in r.heights})
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["id", "height", "n_views", "n_agree", "quality", *extra]
               + [f"{p}_{v}" for v in views for p in ("height", "quality", "reason", "resolved")])
    fmt = lambda x: "" if not np.isfinite(x) else f"{x:.3f}"  # noqa: E731
    for r in rows:
        w.writerow([r.id, fmt(r.height), r.n_views, r.n_agree, f"{r.quality:.3f}",
                    *(c.get(r.id, "") for c in extra.values())]
                   + [x for v in views for x in (fmt(r.heights.get(v, math.nan)), f"{r.qualities.get(v, 0.0):.3f}",
                                                 r.reasons.get(v, "missing"), int(r.views[v].resolved) if v in r.views
                                                 else 0)])
    write_text(path, buf.getvalue())


def find_maps(maps_dir: str | Path) -> dict[str, Path]:
    """{perspective id: path} of the ``<id>.tif`` maps in a folder."""
    import re

    maps_dir = Path(maps_dir)
    if not maps_dir.is_dir():
        raise InputFileError(maps_dir, "no such folder")
    found = {p.stem: p for p in sorted(maps_dir.glob("*.tif")) if re.fullmatch(ID_PATTERN, p.stem)}
    if NADIR_ID not in found:
        raise InputFileError(maps_dir, f"no nadir map {NADIR_ID}.tif (found: {', '.join(sorted(found)) or 'none'})")
    if len(found) < 2:
        raise InputFileError(maps_dir, "no oblique map (<azimuth>_<elevation>.tif) beside the nadir map")
    return found


# --------------------------------------------------------------------------- CLI

def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pipeline25d heights", description=__doc__.split("\n\n")[0])
    parser.add_argument("maps_dir", metavar="MAPS_DIR", help="folder with az000_el90.tif and oblique <id>.tif maps")
    parser.add_argument("--footprints", required=True, help="footprint polygons (any OGR vector file)")
    parser.add_argument("--layer", help="layer name (default: the first polygon layer)")
    parser.add_argument("--id-field", help="attribute holding the building id (default: the feature id)")
    parser.add_argument("--out", default="heights.csv", help="output CSV (default: heights.csv)")
    parser.add_argument("--reference", help="CSV with columns id,height: error statistics against it")
    parser.add_argument("--json", nargs="?", const="-", metavar="PATH",
                        help="statistics as JSON: to PATH, or to stdout (instead of the text lines) without one")
    parser.add_argument("--max-height", type=float, default=MatchSettings.max_height,
                        help="highest building searched for (m, default %(default)g)")
    parser.add_argument("--ring", type=int, default=MatchSettings.ring_px,
                        help="ring width outside the footprint (px, default %(default)d)")
    return parser


def run(maps_dir: str | Path, footprints: str | Path, out: str | Path, layer: str | None = None,
        id_field: str | None = None, reference: str | Path | None = None,
        settings: MatchSettings | None = None) -> dict[str, Any]:
    """Measure every footprint on the maps in ``maps_dir``, write the CSV ``out`` (atomically).

    Returns counts (per view too) and, with a ``reference`` CSV (id,height), its error
    statistics (see :func:`compare`). Raises InputFileError naming the file for a missing or
    unreadable input, footprints that do not overlap the maps (a CRS mismatch, typically).
    """
    maps = find_maps(maps_dir)
    nad = _open(maps[NADIR_ID])
    fps = read_footprints(footprints, layer, id_field, crs=nad.GetProjection() or None)
    if not fps:
        raise InputFileError(footprints, "no footprint polygons")
    ext = dataset_bounds(nad)
    if not any(b[0] < ext[2] and b[2] > ext[0] and b[1] < ext[3] and b[3] > ext[1] for b in (f.bounds for f in fps)):
        raise InputFileError(footprints, "no footprint overlaps the maps (extent "
                             f"{tuple(round(v, 1) for v in ext)}); is the layer in the maps' CRS?")
    ref = read_reference(reference) if reference else None
    s = settings or MatchSettings()
    rows = measure_heights({k: str(v) for k, v in maps.items()}, fps, settings=s)
    write_csv(out, rows)
    views = sorted({k for r in rows for k in r.heights})
    stats: dict[str, Any] = {
        "maps": str(maps_dir), "footprints": str(footprints), "out": str(out),
        "n_footprints": len(rows), "n_measured": sum(1 for r in rows if np.isfinite(r.height)),
        "n_measured_per_view": {v: sum(1 for r in rows if np.isfinite(r.heights.get(v, math.nan))) for v in views},
        "settings": dict(s.__dict__)}
    if ref is not None:
        stats["reference"] = {"path": str(reference), **compare(rows, ref)}
    return stats


def summary_lines(stats: dict[str, Any]) -> list[str]:
    """Human-readable lines of :func:`run`'s statistics."""
    lines = [f"{stats['n_footprints']} footprints, {stats['n_measured']} measured -> {stats['out']}"]
    ref = stats.get("reference")
    if ref:
        for key in ["combined"] + [k for k in ref if k.startswith("az")]:
            st = ref[key]
            if st["n"]:
                lines.append(f"{key}: n {st['n']}, bias {st['bias']:+.3f} m, rmsd {st['rmsd']:.3f} m, "
                             f"median |err| {st['median_abs']:.3f} m, p90 {st['p90_abs']:.3f} m, "
                             f"within 0.5 m {st['within_0.5m']:.1%}")
            else:
                lines.append(f"{key}: n 0 (no measured building in the reference)")
    return lines


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        stats = run(args.maps_dir, args.footprints, args.out, args.layer, args.id_field, args.reference,
                    MatchSettings(max_height=args.max_height, ring_px=args.ring))
    except (Pipeline25dError, RuntimeError) as exc:
        print(f"heights: error: {exc}", file=sys.stderr)
        return 1
    if args.json == "-":
        print(json.dumps(stats, indent=1))
    else:
        print("\n".join(summary_lines(stats)), flush=True)
        if args.json:
            from pipeline25d.core.atomic import write_json

            write_json(args.json, stats)
    return 0


if __name__ == "__main__":
    sys.exit(main())
