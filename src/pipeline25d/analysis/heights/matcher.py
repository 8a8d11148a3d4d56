"""One footprint on one oblique map: the coarse scan of the roof's move, its peaks checked, the sub-pixel fit."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from pipeline25d.analysis.heights.results import MatchSettings
from pipeline25d.analysis.heights.template import _PAD, Template

log = logging.getLogger(__name__)


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
    method: str = "colour"        # colour (the roof's template) or silhouette (where the building ends)


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
