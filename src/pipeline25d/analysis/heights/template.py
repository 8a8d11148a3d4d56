"""A footprint's template on the nadir map: its roof pixels and the ring of different colour around it."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline25d.analysis.evaluate.rasters import _open, _pair_grids, _same_crs
from pipeline25d.analysis.heights.results import MatchSettings
from pipeline25d.core.errors import CRSError
from pipeline25d.core.grid import Grid, Window
from pipeline25d.formats.footprints import Footprint, contains, rasterize
from pipeline25d.geometry.camera import horizontal_direction, relief_factor
from pipeline25d.geometry.perspectives import Perspective

log = logging.getLogger(__name__)


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
    t = Grid.of_dataset(nad).transform
    pair = _pair_grids(obl, nad, path)
    d = horizontal_direction(p)
    d_px = np.array([d[1] / t.e, d[0] / t.a])
    offset = np.array([pair.obl_off[1] - pair.nad_off[1] - pair.frac[1],
                       pair.obl_off[0] - pair.nad_off[0] - pair.frac[0]], dtype=np.float64)
    return _View(pid, relief_factor(p), d_px, pair.src, offset)


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


def _window_index(grid: Grid, win: Window, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(2, n) fractional (row, col) of world (x, y) in the window's pixel array (centres at integers)."""
    cols, rows = grid.colrow(x, y)
    return np.stack([rows - 0.5 - win.row0, cols - 0.5 - win.col0])


def build_template(fp: Footprint, grid: Grid, win: Window, nad_rgb: np.ndarray,
                   nad_alpha: np.ndarray, settings: MatchSettings) -> Template | str:
    """The matching template of ``fp`` from the nadir window ``win`` of ``grid`` (its pixels
    ``nad_rgb``, ``nad_alpha``); a reason string if unusable."""
    from scipy import ndimage

    s, col0, row0 = settings, win.col0, win.row0
    mask = rasterize(fp, grid, win)
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
    gsd = grid.res
    x, y = grid.xy(col0 + tc + 0.5, row0 + tr + 0.5)
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
        pin, pout = _window_index(grid, win, xin, yin), _window_index(grid, win, xout, yout)
        r_n, x_n = _sample(nad_rgb, *pin), _sample(nad_rgb, *pout)
        contrast2 = np.sum((r_n - x_n) ** 2, axis=1)
        ok &= contrast2 > tol2
        a = np.clip(np.sum((colour[near] - x_n) * (r_n - x_n), axis=1) / np.maximum(contrast2, 1e-9), 0.0, 1.0)
        sel = near[ok]
        edge[sel] = True
        p_in[:, sel], p_out[:, sel], cover[sel] = pin[:, ok], pout[:, ok], a[ok]
    return Template(mask, tr, tc, colour, rr, rc, roof, edge, p_in, p_out, cover, deep)
