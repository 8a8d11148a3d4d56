"""A pitched roof's ridge: how far the roof rises above its eave, from where its faces land on an oblique map.

Every point q of a roof is drawn on a terrain-relative oblique map at q + (z(q) − G(q))·cot φ·d
(G: the ground the map subtracted there). With the eave known (the silhouette's level, see
:mod:`.silhouette`), a roof model of rise r puts every nadir roof pixel at a predicted place on the
oblique map; the faces of a pitched roof are shaded apart, so only the right r lands each face on
its own colour. The model: the ridge parallel to the footprint's long side at its middle (the usual
house), ``gabled`` (two faces, rising from the long sides) or ``hipped`` (four faces of one pitch:
the ridge inset by half the short side at both ends); r = 0 is a flat roof. The rise and the kind
are the ones whose landed colours differ least from the nadir colours (truncated quadratic loss, as
the flat matcher's), over rises up to MAX_RISE_M and both kinds; the ridge height is the eave's
plus that rise. Where both faces look alike (the ridge along the light), the silhouette's gable
ends give the rise (:func:`silhouette_roof`). With the ridge known, the eave is the level at which
the silhouette's lines, less what the roof adds above the eave where each line starts
(:func:`line_excess`: the gable's apex, a face steeper than the view), agree (:func:`fit_eave`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pipeline25d.analysis.heights.silhouette import Lines, robust_level
from pipeline25d.analysis.heights.template import Template
from pipeline25d.formats.footprints import Footprint
from pipeline25d.geometry.camera import horizontal_direction
from pipeline25d.geometry.perspectives import Perspective

KINDS = ("gabled", "hipped")
RISE_STEP_M = 0.1
MAX_FIT_PX = 1500            # template pixels the rise is fitted on (every k-th beyond)
COARSE_STEP_M = 0.5           # the rise is scanned at this step first, then at RISE_STEP_M around the best
MAX_RISE_M = 12.0
#: the loss must fall this much (share of the flat roof's) for a rise to count: else the roof is flat
MIN_GAIN = 0.1
#: ... and by this much at least (share of the pixels: a uniform flat roof's loss is near 0 anyway)
MIN_LOSS_DROP = 0.01
#: the silhouette's lines: a rise must make this much larger a share of them agree
MIN_SHARE_GAIN = 0.2
#: ... and a rise up to this × the half width (tan 50°)
MAX_SILHOUETTE_PITCH = 1.2
#: a view whose best loss is above this does not show the roof (hidden): it says nothing
MAX_LOSS = 0.5
#: a view where a flat roof at the eave fits this well says the roof is flat
FLAT_FIT = 0.02


@dataclass(frozen=True)
class RoofFrame:
    """The footprint's minimum-area rectangle: centre, unit vectors along its long and short side,
    half its length and width (m)."""

    centre: np.ndarray
    along: np.ndarray
    across: np.ndarray
    half_length: float
    half_width: float


def roof_frame(fp: Footprint) -> RoofFrame:
    """The minimum-area rectangle around the outer ring, its sides parallel to one of its edges."""
    ring = fp.rings[0]
    best = None
    for a, b in zip(ring, np.roll(ring, -1, axis=0)):
        e = b - a
        n = float(np.hypot(*e))
        if n <= 0:
            continue
        u = e / n
        v = np.array([-u[1], u[0]])
        pu, pv = ring @ u, ring @ v
        area = float(np.ptp(pu) * np.ptp(pv))
        if best is None or area < best[0]:
            best = (area, u, v, pu, pv)
    if best is None:
        c = ring.mean(axis=0)
        return RoofFrame(c, np.array([1.0, 0.0]), np.array([0.0, 1.0]), 0.0, 0.0)
    _, u, v, pu, pv = best
    centre = u * (pu.max() + pu.min()) / 2 + v * (pv.max() + pv.min()) / 2
    lu, lv = float(np.ptp(pu)) / 2, float(np.ptp(pv)) / 2
    if lv > lu:
        u, v, lu, lv = v, -u, lv, lu
    return RoofFrame(centre, u, v, lu, lv)


def rise_share(frame: RoofFrame, kind: str, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height above the eave as a share of the rise (0 at the eave, 1 on the ridge) at (x, y)."""
    q = np.stack([np.asarray(x, np.float64) - frame.centre[0], np.asarray(y, np.float64) - frame.centre[1]], -1)
    w = max(frame.half_width, 1e-9)
    side = (w - np.abs(q @ frame.across)) / w
    end = (frame.half_length - np.abs(q @ frame.along)) / w
    if kind == "hipped":
        side = np.minimum(side, end)
    return np.where(end >= 0, np.clip(side, 0.0, 1.0), 0.0)


@dataclass(frozen=True)
class RiseFit:
    """One view's fit: the rise (m) and kind, the loss of a flat roof at the eave and of the fit."""

    rise: float
    kind: str
    flat_loss: float
    loss: float


NO_FIT = RiseFit(math.nan, "", math.nan, math.nan)


def fit_rise(fp: Footprint, xy: np.ndarray, colour: np.ndarray, sample_oblique: Callable[[np.ndarray], np.ndarray],
             eave_move: np.ndarray | dict[str, np.ndarray], cot: float, tol: float) -> RiseFit:
    """The rise and kind (:class:`RiseFit`) of the roof whose nadir pixels at world ``xy`` (n, 2)
    have ``colour`` (n, 3): ``sample_oblique(u)`` gives the oblique colours (k, n, 3) where each pixel
    lands when moved by u (k, n) metres along d, k candidate moves at once; ``eave_move`` (n,) is
    each pixel's move were it at the eave (its eave height above the ground the map subtracted
    there, × cot φ), or such moves per roof kind (flat, gabled, hipped: the map subtracts the
    ground of each one's vertices, :func:`roof_ground`). Rise 0 and kind ``flat`` when no rise
    lowers the loss by MIN_GAIN of the flat roof's and MIN_LOSS_DROP."""
    frame = roof_frame(fp)
    tol2 = tol * tol

    def losses(moves: np.ndarray) -> np.ndarray:
        """(k,) the loss of each of k candidate moves (k, n) of the pixels, sampled in one call."""
        d2 = np.sum((sample_oblique(moves) - colour) ** 2, axis=-1)
        return np.mean(np.minimum(d2, tol2), axis=-1) / tol2

    moves = eave_move if isinstance(eave_move, dict) else {k: eave_move for k in ("flat", *KINDS)}
    flat = float(losses(moves["flat"][None])[0])
    best = (flat, 0.0, "flat")
    for kind in KINDS:
        share = rise_share(frame, kind, xy[:, 0], xy[:, 1])
        coarse = np.arange(COARSE_STEP_M, MAX_RISE_M + 1e-9, COARSE_STEP_M)
        k = int(np.argmin(losses(moves[kind] + coarse[:, None] * share * cot)))
        rises = np.arange(max(coarse[k] - COARSE_STEP_M, RISE_STEP_M), coarse[k] + COARSE_STEP_M + 1e-9, RISE_STEP_M)
        scores = losses(moves[kind] + rises[:, None] * share * cot)
        k = int(np.argmin(scores))
        r = float(rises[k])
        if 0 < k < len(rises) - 1:                   # parabola through the minimum and its neighbours
            a, b, c = scores[k - 1:k + 2]
            den = a - 2 * b + c
            if den > 0:
                r += 0.5 * (a - c) / den * RISE_STEP_M
        if scores[k] < best[0]:
            best = (float(scores[k]), r, kind)
    gain = (flat - best[0]) / flat if flat > 0 else 0.0
    if best[2] == "flat" or gain < MIN_GAIN or flat - best[0] < MIN_LOSS_DROP:
        return RiseFit(0.0, "flat", flat, flat)
    return RiseFit(best[1], best[2], flat, best[0])


Ground = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _paths(fp: Footprint, kind: str, xy: np.ndarray, d: np.ndarray, cot: float, ground: Ground | None = None,
           step_m: float = 0.25) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(share of the rise, t / cot φ, ground drop) along each line's path back over the roof
    (q = e − t·d). The drop is what the map subtracted at the line's start (the outline, as
    :func:`.silhouette.levelled` adds it back) minus what it subtracted under q, ``ground`` (the
    DTM) there: on ground that falls towards the viewer a roof point behind the outline is drawn
    that much farther out. 0 without ``ground``; −inf where q is off the roof (t > 0)."""
    frame = roof_frame(fp)
    t = np.arange(0.0, 2.0 * (frame.half_length + frame.half_width) + step_m, step_m)
    qx, qy = xy[:, 0, None] - t[None, :] * d[0], xy[:, 1, None] - t[None, :] * d[1]
    share = rise_share(frame, kind, qx, qy)
    drop = np.zeros_like(share)
    if ground is not None:
        from pipeline25d.analysis.heights.silhouette import outline_ground

        cx, cy = qx - frame.centre[0], qy - frame.centre[1]
        on = ((np.abs(cx * frame.across[0] + cy * frame.across[1]) <= frame.half_width + 0.05)
              & (np.abs(cx * frame.along[0] + cy * frame.along[1]) <= frame.half_length + 0.05))
        g = roof_ground(frame, kind, ground, qx, qy, share)
        drop = np.where(on & np.isfinite(g), outline_ground(fp, xy, ground)[:, None] - g, -np.inf)
        drop[:, 0] = 0.0
    return share, t[None, :] / cot, drop


def roof_ground(frame: RoofFrame, kind: str, ground: Ground, x: np.ndarray, y: np.ndarray,
                share: np.ndarray) -> np.ndarray:
    """The ground a terrain-relative map subtracted under roof points (x, y): the renderer takes the
    DTM at the roof's vertices (eave corners, ridge ends) and interpolates it across each face, so
    here the eave's ground (linear along its edge between two corners) and the ridge's (linear
    between its ends), mixed by the point's ``share`` of the rise."""
    c, u, v = frame.centre, frame.along, frame.across
    L, W = frame.half_length, frame.half_width
    corner = {(a, b): float(ground(*(c + a * L * u + b * W * v)[:, None])[0]) for a in (-1, 1) for b in (-1, 1)}
    qx, qy = x - c[0], y - c[1]
    a, b = qx * u[0] + qy * u[1], qx * v[0] + qy * v[1]

    def lerp(g0, g1, t):
        return g0 + (g1 - g0) * (t + 1.0) / 2.0

    if kind == "flat":                                # the four corners', bilinear
        pa, pc = np.clip(a / max(L, 1e-9), -1.0, 1.0), np.clip(b / max(W, 1e-9), -1.0, 1.0)
        return lerp(lerp(corner[(-1, -1)], corner[(1, -1)], pa), lerp(corner[(-1, 1)], corner[(1, 1)], pa), pc)
    # the point's place on its level's outline (half extents L − s·W, W·(1 − s) on a hipped roof,
    # L, W·(1 − s) on a gabled one), carried down its face to the eave and up to the ridge
    s = np.clip(share, 0.0, 1.0)
    hipped = kind == "hipped"
    pa = np.clip(a / np.maximum(L - s * W if hipped else L, 1e-9), -1.0, 1.0)
    pc = np.clip(b / np.maximum(W * (1.0 - s), 1e-9), -1.0, 1.0)
    up = b >= 0
    eave = lerp(np.where(up, corner[(-1, 1)], corner[(-1, -1)]), np.where(up, corner[(1, 1)], corner[(1, -1)]), pa)
    r = L
    if hipped:
        r = max(L - W, 0.0)
        ahead = a >= 0
        end = lerp(np.where(ahead, corner[(1, -1)], corner[(-1, -1)]),
                   np.where(ahead, corner[(1, 1)], corner[(-1, 1)]), pc)
        eave = np.where(L - np.abs(a) < W - np.abs(b), end, eave)
    ends = np.stack([c - r * u, c + r * u])
    g_ends = ground(ends[:, 0], ends[:, 1])
    ridge = lerp(g_ends[0], g_ends[1], pa if r > 0 else 0.0 * pa)
    return (1.0 - share) * eave + share * ridge


def _excess(paths: tuple[np.ndarray, np.ndarray, np.ndarray], rise: float) -> np.ndarray:
    """:func:`line_excess` on paths of :func:`_paths`."""
    share, back, drop = paths
    return np.max(rise * share + drop - back, axis=1)


def line_excess(fp: Footprint, kind: str, rise: float, xy: np.ndarray, d: np.ndarray, cot: float,
                ground: Ground | None = None) -> np.ndarray:
    """How much higher than the eave each silhouette line from outline points ``xy`` (n, 2) ends, in
    metres of height, on a roof of ``kind`` rising ``rise`` m: the roof point behind the line's start
    (q = e − t·d) drawn farthest along d, max over t of rise·share(q) + ground drop − t / cot φ (0 on
    an eave on level ground, up to the rise at a gable end, more where the roof, or the ground under
    it, is steeper than the view; see :func:`_paths` for the drop)."""
    return _excess(_paths(fp, kind, xy, d, cot, ground), rise)


def silhouette_roof(fp: Footprint, views: list[tuple[np.ndarray, np.ndarray, np.ndarray, float]],
                    inlier: float, ground: Ground | None = None) -> tuple[str, float, float, float]:
    """(kind, rise, eave, share of lines agreeing) of the roof whose levelled silhouette lines
    (``views``: (outline points, heights, d, cot φ) per view) end where a gabled roof of that rise
    (up to a pitch of MAX_SILHOUETTE_PITCH) over one eave ends them, for the most lines; kind
    ``flat`` (rise 0) unless a rise makes at least MIN_SHARE_GAIN more of the lines agree. Only a
    gable end (a wall up to the ridge) on a far outline shows a rise: a hip end's slope, gentler
    than the view, ends its lines at the eave, and lines that other buildings lengthen would
    pass for one. ``ground``: the DTM (see :func:`line_excess`)."""
    h = np.concatenate([v[1] for v in views])
    paths = [_paths(fp, "gabled", xy, d, cot, ground) for xy, _, d, cot in views]

    def level(rise: float) -> tuple[float, float]:
        return robust_level(h - np.concatenate([_excess(p, rise) for p in paths]), inlier)

    eave, share = level(0.0)
    best = ("flat", 0.0, eave, share)
    top = min(MAX_RISE_M, roof_frame(fp).half_width * MAX_SILHOUETTE_PITCH)
    for rise in np.arange(COARSE_STEP_M / 2, top + 1e-9, COARSE_STEP_M / 2):
        e, sh = level(float(rise))
        if sh > best[3] + (MIN_SHARE_GAIN if best[0] == "flat" else 0.0):
            best = ("gabled", float(rise), e, sh)
    return best


def lines_roof(fp: Footprint, lines: dict[str, Lines | str], cot: dict[str, float],
               ground: Ground | None = None) -> tuple[str, float, float, float]:
    """:func:`silhouette_roof` on every view's levelled lines ({perspective id: Lines, or why
    none}; ``cot``: cot φ per view); kind "" where no view has lines."""
    usable = [(lv.xy, lv.h, horizontal_direction(Perspective.from_id(p)), cot[p], lv.inlier)
              for p, lv in lines.items() if isinstance(lv, Lines)]
    if not usable:
        return "", math.nan, math.nan, 0.0
    return silhouette_roof(fp, [u[:4] for u in usable], max(u[4] for u in usable), ground)

def fit_eave(fp: Footprint, kind: str, ridge: float, xy: np.ndarray, h: np.ndarray, d: np.ndarray, cot: float,
             inlier: float, ground: Ground | None = None) -> tuple[float, float]:
    """(eave, share of lines agreeing) of a pitched roof whose ``ridge`` is known, from one view's
    levelled silhouette lines (outline points ``xy``, heights ``h``): the eave e whose roof (rising
    ridge − e) ends every line where it ends, h ≈ e + :func:`line_excess`, for the most lines (the
    eave's own lines pin e; a gable end's lines agree only with the right e as well). ``ground``:
    the DTM (see :func:`line_excess`)."""
    paths = _paths(fp, kind, xy, d, cot, ground)
    best = (-1.0, math.inf, math.nan)
    for e in np.arange(ridge, ridge - MAX_RISE_M - 1e-9, -COARSE_STEP_M / 5):
        r = h - e - _excess(paths, ridge - e)
        share = float(np.mean(np.abs(r) <= inlier))
        spread = float(np.mean(np.abs(r)))
        if (share, -spread) > (best[0], -best[1]):
            best = (share, spread, float(e))
    share, _, e = best
    near = np.abs(h - e - _excess(paths, ridge - e)) <= inlier
    if near.any():                                    # the level of the agreeing lines, unrounded
        e += float(np.mean((h - e - _excess(paths, ridge - e))[near]))
    return e, share


def view_rise(fp: Footprint, tmpl: Template, xy: np.ndarray, obl_rgb: np.ndarray, off: np.ndarray, d_px: np.ndarray,
              cot: float, eave: float, ground_excess: dict[str, np.ndarray], tol: float) -> RiseFit:
    """:func:`fit_rise` on one oblique view: the template's pixels deeper than 2.5 px inside the
    outline (no mixed edge pixels; at most about MAX_FIT_PX of them, evenly) at world ``xy``;
    ``eave`` the building's eave height above the mean ground under it, ``ground_excess``: per roof
    kind (flat, gabled, hipped) the ground the map subtracted at each pixel minus that mean (n,)
    (:func:`roof_ground`; zeros without a DTM)."""
    deep = np.flatnonzero(tmpl.deep)
    if len(deep) < 16:
        return NO_FIT
    deep = deep[::-(-len(deep) // MAX_FIT_PX)]           # an even subset: the cost stays per building
    from scipy import ndimage

    rows, cols, colour = tmpl.rows[deep] + off[0], tmpl.cols[deep] + off[1], tmpl.colour[deep]
    moves = {k: (eave - g[deep]) * cot for k, g in ground_excess.items()}
    move = np.minimum.reduce(list(moves.values()))
    # the part of the window the moves reach (eave .. eave + MAX_RISE_M), as float64 once
    ends = [(rows + u * d_px[0], cols + u * d_px[1])
            for u in (move, np.maximum.reduce(list(moves.values())) + MAX_RISE_M * cot)]
    r0 = max(int(min(e[0].min() for e in ends)) - 2, 0)
    c0 = max(int(min(e[1].min() for e in ends)) - 2, 0)
    r1 = min(int(max(e[0].max() for e in ends)) + 3, obl_rgb.shape[0])
    c1 = min(int(max(e[1].max() for e in ends)) + 3, obl_rgb.shape[1])
    if r1 <= r0 or c1 <= c0:
        return NO_FIT
    bands = [obl_rgb[r0:r1, c0:c1, ch].astype(np.float64) for ch in range(3)]

    def sample(u: np.ndarray) -> np.ndarray:          # (k, n) moves -> (k, n, 3) colours
        at = np.stack([rows + u * d_px[0] - r0, cols + u * d_px[1] - c0])
        return np.stack([ndimage.map_coordinates(b, at, order=1, mode="nearest") for b in bands], axis=-1)

    return fit_rise(fp, xy[deep], colour, sample, moves, cot, tol)


def ridge_height(fits: dict[str, RiseFit], eave: float) -> tuple[float, str]:
    """(ridge height, roof kind) of a building from its views' :func:`view_rise`. Views whose best
    loss is above MAX_LOSS do not show the roof; a view where the flat roof fits within FLAT_FIT
    and no rise fits clearly better (its fit's kind is flat) makes it flat (a view whose faces
    look alike fits a flat roof well too, but then another view's rise decides); else the kind of
    the view that gained most and the eave plus the median rise of the views that found one.
    Without a view that shows the roof: unmeasured."""
    seen = [f for f in fits.values() if math.isfinite(f.loss) and f.loss <= MAX_LOSS]
    if not seen or not math.isfinite(eave):
        return math.nan, ""
    pitched = [f for f in seen if f.kind != "flat"]
    if not pitched or any(f.flat_loss <= FLAT_FIT and f.kind == "flat" for f in seen):
        return eave, "flat"
    best = max(pitched, key=lambda f: f.flat_loss - f.loss)
    return eave + float(np.median([f.rise for f in pitched])), best.kind
