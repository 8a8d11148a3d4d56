"""Where GCP candidates go: exposed, locally planar ground, clear along every view, evenly spread.

Inputs are the scene's DSM (the model's top surface, from the nadir render) and DTM on one
grid. A cell is a possible site where

* the surface is ground: |DSM − DTM| ≤ ``max_height`` m;
* it is exposed: no above-ground cell within marker radius + ``clearance`` m (the paper
  leaves out "areas surrounding buildings");
* the ground is locally planar (the DSM deviates from its own local mean by at most
  ``max_roughness`` m over the marker) and no steeper than ``max_slope`` degrees;
* the line of sight toward the camera stays above the DSM in at least one requested view
  (checked for the marker's centre and its two side rims).

The scene is divided into squares of ``spacing`` metres; each square gets the valid site seen
in the most views, nearest its centre among equals, so candidates are evenly spread at the
configured density. A check square counts the default perspectives' views, not the config's
(the DTM leaves its site's ground out, and must not move with the perspectives). The render
still decides per view (see :mod:`pipeline25d.stages.render`): this only avoids wasting candidates.

The per-cell tests run block by block (blocks of whole squares, each read with the few cells
its tests reach beyond it), so their memory follows a block; the lines of sight read the whole
DSM, which may be float32.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pipeline25d.core.grid import Block, Grid, cell_blocks
from pipeline25d.geometry.perspectives import PRESETS, Perspective

OPTIONS_PER_SQUARE = 6       # nearest-to-centre sites tested for line of sight per square
#: the views a check square's options are ranked by (the default perspectives), not the config's
REFERENCE_VIEWS = [Perspective(az, el) for az, el in PRESETS["eight-45+nadir"]]
SIGHT_MARGIN_M = 0.05        # the DSM must stay this far below a line of sight
MAX_SIGHT_M = 400.0          # longest line of sight checked (horizontal metres)
SITE_BLOCK_CELLS = 1 << 20   # cells of a block of the per-cell tests (~100 bytes a cell)


@dataclass(frozen=True)
class SiteRules:
    """Thresholds of :func:`select_sites` (metres and degrees)."""

    spacing: float
    radius: float              # marker radius on the ground
    clearance: float = 1.0
    max_height: float = 0.2
    max_roughness: float = 0.05
    max_slope: float = 30.0


def ground_mask(dsm: np.ndarray, dtm: np.ndarray, max_height: float) -> np.ndarray:
    """Cells whose top surface is the ground: |DSM − DTM| ≤ max_height."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(dsm) & np.isfinite(dtm) & (np.abs(dsm - dtm) <= max_height)


def local_slope(dsm: np.ndarray, k: int, res: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(dz/dx, dz/dy, roughness) per cell over a (2k+1)² window; x east, y north.

    Slopes are central differences across the window; roughness is |DSM − window mean|,
    which is zero on any plane and grows with curvature and clutter.
    """
    from scipy import ndimage as ndi

    sx = np.full(dsm.shape, np.nan)
    sy = np.full(dsm.shape, np.nan)
    sx[:, k:-k] = (dsm[:, 2 * k:] - dsm[:, :-2 * k]) / (2 * k * res)
    sy[k:-k, :] = (dsm[:-2 * k, :] - dsm[2 * k:, :]) / (2 * k * res)   # row 0 is north
    mean = ndi.uniform_filter(np.nan_to_num(dsm), size=2 * k + 1, mode="nearest")
    return sx, sy, np.abs(dsm - mean)


def select_sites(dsm: np.ndarray, dtm: np.ndarray, grid: Grid, rules: SiteRules,
                 perspectives: list[Perspective], max_cells: int = SITE_BLOCK_CELLS,
                 check_square: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Candidate sites: arrays x, y, z (DSM at the site), ground (DTM), sx, sy (slopes),
    square_col/square_row (the spacing square) and clear ((n, len(perspectives)) bool: the
    lines of sight of that view are clear); and held_x, held_y, held_col, held_row: the check
    squares' sites, whose ground the DTM leaves out.

    ``dsm``, ``dtm``: (height, width) of ``grid``, float64 or float32 (tests run in float64).
    ``check_square``: which squares (arrays of cols, rows) hold check points
    (:func:`pipeline25d.stages.gcps.check_squares`; None: none). The check squares' sites are
    those the default perspectives (REFERENCE_VIEWS) choose, whatever the config has: so the
    ground the DTM leaves out, and the DTM, do not move when a perspective is added or removed
    (every tile would be drawn again). With the default perspectives, the config's own sites.
    A check site the config's views drop (hidden in all, or too near another for them) gives no
    candidate but stays held out; one the reference drops is no check point in any config.
    """
    xs, ys = grid.column_x(), grid.row_y()
    k = max(1, int(math.ceil(rules.radius / grid.res)))
    margin = max(k, int(math.ceil((rules.radius + rules.clearance) / grid.res))) + 1
    cuts = [np.flatnonzero(np.diff(np.floor(v / rules.spacing))) + 1 for v in (ys, xs)]   # square edges
    blocks = cell_blocks(grid.height, grid.width, margin, max_cells, *cuts)
    # blocks of empty land (a sparse scene) hold no site: skipped, but one keeps the result's keys
    with_model = [b for b in blocks if np.isfinite(dsm[b.window]).any()] or blocks[:1]
    parts = [_square_options(dsm, dtm, grid, rules, block, k) for block in with_model]
    o = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    slopes = np.column_stack([o["sx"], o["sy"]])
    clear = _clear_lines_of_sight(dsm, grid, o["x"], o["y"], o["z"], slopes, rules.radius, perspectives)
    checks = check_square(o["sq_x"], o["sq_y"]) if check_square is not None else np.zeros(len(clear), bool)
    if not checks.any():
        return {**_chosen(o, clear.sum(axis=1), clear, grid, rules, perspectives), **_held(None)}
    same = sorted(p.id for p in perspectives) == sorted(p.id for p in REFERENCE_VIEWS)
    reference = clear if same else _clear_lines_of_sight(dsm, grid, o["x"], o["y"], o["z"], slopes, rules.radius,
                                                         REFERENCE_VIEWS)
    ref = _chosen(o, reference.sum(axis=1), reference, grid, rules, REFERENCE_VIEWS)
    held = check_square(ref["square_col"], ref["square_row"])
    # a check square takes the reference's site; one the reference does not keep gives no site
    # (the default perspectives: the reference's sites are the config's, chosen and thinned alike)
    sites = ref if same else _chosen(o, np.where(checks, reference.sum(axis=1), clear.sum(axis=1)), clear, grid,
                                     rules, perspectives)
    kept = set(zip(ref["square_col"][held].tolist(), ref["square_row"][held].tolist()))
    ok = ~check_square(sites["square_col"], sites["square_row"]) | np.array(
        [sq in kept for sq in zip(sites["square_col"].tolist(), sites["square_row"].tolist())], dtype=bool)
    return {**{key: v[ok] for key, v in sites.items()}, **_held(ref, held)}


def _held(ref: dict[str, np.ndarray] | None, held: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The held_* arrays of :func:`select_sites`: the reference's sites where ``held`` (None: empty)."""
    if ref is None:
        return {"held_x": np.zeros(0), "held_y": np.zeros(0), "held_col": np.zeros(0, np.int64),
                "held_row": np.zeros(0, np.int64)}
    return {"held_x": ref["x"][held], "held_y": ref["y"][held], "held_col": ref["square_col"][held],
            "held_row": ref["square_row"][held]}


def _chosen(o: dict[str, np.ndarray], rank: np.ndarray, clear: np.ndarray, grid: Grid, rules: SiteRules,
            perspectives: list[Perspective]) -> dict[str, np.ndarray]:
    """The sites of :func:`select_sites` among the options ``o`` of every square: per square the
    option of the highest ``rank`` (views that see it), nearest the centre among equals; kept
    where one of ``clear``'s views sees it (each view's render rejects what it cannot see) and
    thinned so that no two markers touch in ``perspectives``."""
    by_rank = np.lexsort((o["dist"], -rank, o["sq_y"], o["sq_x"]))
    first = by_rank[_starts_of_runs(o["sq_x"][by_rank], o["sq_y"][by_rank])]
    first = first[clear[first].any(axis=1)]
    o, clear = {key: v[first] for key, v in o.items()}, clear[first]
    # Off the cell centre by a fraction of a cell (a hash of the square, so stable): markers
    # centred on pixel corners would give exact centroids and hide the method's own resolution.
    jx, jy = _jitter(o["sq_x"], o["sq_y"])
    px, py = o["x"] + jx * grid.res, o["y"] + jy * grid.res
    slopes = np.column_stack([o["sx"], o["sy"]])
    # which of two close sites survives follows a hash of their squares, not sites elsewhere
    apart = _apart(px, py, slopes, np.lexsort((o["sq_y"], o["sq_x"], jx)), rules.radius, grid.res, perspectives)
    o, clear, jx, jy, px, py = ({key: v[apart] for key, v in o.items()}, clear[apart], jx[apart], jy[apart],
                                px[apart], py[apart])
    dz = o["sx"] * jx * grid.res + o["sy"] * jy * grid.res   # along the local ground plane
    return {"x": px, "y": py, "z": o["z"] + dz, "ground": o["ground"] + dz, "sx": o["sx"], "sy": o["sy"],
            "square_col": o["sq_x"].astype(np.int64), "square_row": o["sq_y"].astype(np.int64),
            "clear": clear}


def _square_options(dsm: np.ndarray, dtm: np.ndarray, grid: Grid, rules: SiteRules, block: Block,
                    k: int) -> dict[str, np.ndarray]:
    """The OPTIONS_PER_SQUARE valid sites nearest its centre of each square in ``block``'s core
    (whole squares), as arrays x, y, z, ground, sx, sy, sq_x, sq_y and dist (to the square's centre)."""
    from scipy import ndimage as ndi

    d = np.asarray(dsm[block.window], dtype=np.float64)
    t = np.asarray(dtm[block.window], dtype=np.float64)
    ground = ground_mask(d, t, rules.max_height)
    # exposed: distance to the nearest non-ground cell, in metres (the window reaches past that distance)
    if ground.all() and block.window != block.core:
        exposed = ground
    else:
        exposed = ndi.distance_transform_edt(ground) * grid.res >= rules.radius + rules.clearance
    sx, sy, rough = local_slope(d, k, grid.res)
    with np.errstate(invalid="ignore"):
        slope_deg = np.degrees(np.arctan(np.hypot(sx, sy)))
        ok = exposed & (rough <= rules.max_roughness) & (slope_deg <= rules.max_slope)
    inner = block.inner
    rows, cols = np.nonzero(ok[inner])
    wr, wc = rows + inner[0].start, cols + inner[1].start
    x, y = grid.column_x()[cols + block.core[1].start], grid.row_y()[rows + block.core[0].start]
    sq_x, sq_y = np.floor(x / rules.spacing), np.floor(y / rules.spacing)
    dist = np.hypot(x - (sq_x + 0.5) * rules.spacing, y - (sq_y + 0.5) * rules.spacing)
    order = np.lexsort((dist, sq_y, sq_x))
    first = _starts_of_runs(sq_x[order], sq_y[order])
    rank = np.arange(len(order)) - np.maximum.accumulate(np.where(first, np.arange(len(order)), 0))
    o = order[rank < OPTIONS_PER_SQUARE]
    r, c = wr[o], wc[o]
    return {"x": x[o], "y": y[o], "z": d[r, c], "ground": t[r, c], "sx": sx[r, c], "sy": sy[r, c],
            "sq_x": sq_x[o], "sq_y": sq_y[o], "dist": dist[o]}


def _apart(x: np.ndarray, y: np.ndarray, slopes: np.ndarray, order: np.ndarray, radius: float, res: float,
           perspectives: list[Perspective]) -> np.ndarray:
    """(n,) bool: a subset of sites whose marker images cannot touch in any view, kept greedily in ``order``.

    A marker's image reaches radius·σ_max(I + cot φ·d ⊗ slope) (+ one DSM cell) from its
    centre (the same bound the render uses to reject overlaps); ``slopes`` is (n, 2).
    """
    from scipy.spatial import cKDTree

    from pipeline25d.geometry.camera import image_stretch

    n = len(x)
    if n < 2:
        return np.ones(n, dtype=bool)
    stretch = np.ones(n)
    for p in perspectives:
        stretch = np.maximum(stretch, image_stretch(p, slopes))
    reach = radius * stretch + res
    tree = cKDTree(np.column_stack([x, y]))
    kept = np.zeros(n, dtype=bool)
    for i in order:
        near = tree.query_ball_point([x[i], y[i]], reach[i] + reach.max())
        if not any(kept[j] and np.hypot(x[i] - x[j], y[i] - y[j]) < reach[i] + reach[j] for j in near):
            kept[i] = True
    return kept


def _starts_of_runs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) bool: where the sorted key pair (a, b) differs from the previous entry."""
    if not len(a):
        return np.zeros(0, dtype=bool)
    return np.r_[True, (a[1:] != a[:-1]) | (b[1:] != b[:-1])]


def _jitter(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic offsets in [-0.4, 0.4) per integer pair (a, b), by an integer hash."""
    h = (a.astype(np.int64) * 73856093) ^ (b.astype(np.int64) * 19349663)
    h = (h * 2654435761) % (2 ** 32)
    return (h % 1000) / 1000 * 0.8 - 0.4, ((h // 1000) % 1000) / 1000 * 0.8 - 0.4


def _clear_lines_of_sight(dsm: np.ndarray, grid: Grid, x: np.ndarray, y: np.ndarray, z: np.ndarray,
                          slopes: np.ndarray, radius: float, perspectives: list[Perspective],
                          batch: int = 4096) -> np.ndarray:
    """(n, len(perspectives)) bool: whether, in each perspective, the rays to the camera from
    the site's centre and side rims stay SIGHT_MARGIN_M above the DSM (nearest-cell samples;
    outside = clear; nadir is always clear).

    Rim heights follow the site's ground plane (``slopes``: (n, 2) dz/dx, dz/dy).
    """
    top = np.nanmax(dsm) if np.isfinite(dsm).any() else 0.0
    clear = np.ones((len(x), len(perspectives)), dtype=bool)
    for v, p in enumerate(perspectives):
        if p.elevation == 90:
            continue
        ok = clear[:, v]
        t_ = math.radians(p.azimuth)
        back = -np.array([math.sin(t_), math.cos(t_)])          # from the site toward the camera
        side = np.array([back[1], -back[0]])
        tan_e = math.tan(math.radians(p.elevation))
        for lo in range(0, len(x), batch):
            idx = np.arange(lo, min(lo + batch, len(x)))
            idx = idx[ok[idx]]
            if not len(idx):
                continue
            reach = np.minimum((top - z[idx]) / tan_e, MAX_SIGHT_M)
            steps = np.arange(grid.res, max(float(reach.max()), grid.res) + grid.res, grid.res)
            for off in (0.0, radius, -radius):
                ox, oy = x[idx] + off * side[0], y[idx] + off * side[1]
                oz = z[idx] + off * (slopes[idx, 0] * side[0] + slopes[idx, 1] * side[1])
                blocked = _ray_blocked(dsm, grid, ox, oy, oz, back, tan_e, steps, reach)
                ok[idx[blocked]] = False
    return clear


def _ray_blocked(dsm: np.ndarray, grid: Grid, x: np.ndarray, y: np.ndarray, z: np.ndarray, back: np.ndarray,
                 tan_e: float, steps: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """Whether the DSM rises above each ray (x, y, z) + t·(back, tan_e), t in steps ≤ reach."""
    h, w = dsm.shape
    px = x[:, None] + steps[None] * back[0]
    py = y[:, None] + steps[None] * back[1]
    col, row = (np.floor(v).astype(np.int64) for v in grid.colrow(px, py))
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h) & (steps[None] <= reach[:, None])
    surf = np.full(px.shape, -np.inf)
    surf[inside] = dsm[row[inside], col[inside]]
    surf = np.nan_to_num(surf, nan=-np.inf)
    return np.any(surf > z[:, None] + steps[None] * tan_e - SIGHT_MARGIN_M, axis=1)
