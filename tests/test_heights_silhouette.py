"""The silhouette's end as a height: a roof tinted like its walls, on ground sloping under it.

Synthetic maps drawn here (no renderer): textured ground that the nadir and the oblique maps
share, and on each oblique map the building's sweep painted in ONE colour (roof and walls alike),
its far end moved by (roof − ground at that outline point)·cot φ, the way a terrain-relative map
draws a flat roof over a sloped DTM. The truth is the analytic mean of that linear ground over
the footprint: the roof minus the ground at the footprint's area centroid.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline25d.analysis.heights.results import MatchSettings
from pipeline25d.analysis.heights.silhouette import (
    area_centroid,
    levelled,
    outline_ground,
    plane_fit,
    roof_heights,
    silhouette_lines,
)
from pipeline25d.core.grid import Extent, Grid
from pipeline25d.formats.footprints import Footprint, contains
from pipeline25d.geometry.camera import horizontal_direction, relief_factor
from pipeline25d.geometry.perspectives import Perspective

GSD = 0.5
SIZE = 240                                   # px
ROOF = np.array([120.0, 118.0, 121.0])
ROOF_Z, GX, GY = 30.0, 0.35, -0.2            # roof z; ground z = GX·x + GY·y (x, y from the scene centre)
VIEWS = ("az045_el45", "az200_el30")


def _ground(rng: np.random.Generator) -> np.ndarray:
    base = rng.integers(0, 4, size=(SIZE // 4, SIZE // 4))
    palette = np.array([[60, 140, 50], [170, 160, 80], [130, 90, 60], [40, 80, 30]], np.uint8)
    return np.kron(palette[base], np.ones((4, 4, 1), np.uint8)).astype(np.uint8)


def _footprint() -> Footprint:
    c, s = math.cos(math.radians(23)), math.sin(math.radians(23))
    local = np.array([[-9.0, -6.0], [9.0, -6.0], [9.0, 6.0], [-9.0, 6.0]])
    return Footprint("b", (local @ np.array([[c, s], [-s, c]]),))


def _oblique(ground: np.ndarray, fp: Footprint, grid: Grid, pid: str) -> np.ndarray:
    """The ground with the building's sweep painted ROOF: pixel centres m with m = p + t·d for a
    footprint point p and 0 ≤ t ≤ (ROOF_Z − ground(p))·cot φ."""
    p = Perspective.from_id(pid)
    d, cot = horizontal_direction(p), relief_factor(p)
    xs, ys = grid.xy(np.arange(SIZE)[None, :] + 0.5, np.arange(SIZE)[:, None] + 0.5)
    xs, ys = np.broadcast_to(xs, (SIZE, SIZE)).ravel(), np.broadcast_to(ys, (SIZE, SIZE)).ravel()
    reach = 40.0 * cot
    lo, hi = (np.minimum(fp.bounds[:2], np.add(fp.bounds[:2], reach * d)),
              np.maximum(fp.bounds[2:], np.add(fp.bounds[2:], reach * d)))
    near = np.flatnonzero((xs >= lo[0]) & (xs <= hi[0]) & (ys >= lo[1]) & (ys <= hi[1]))
    # m − t·d inside F with t ≤ H(m − t·d)·cot: march t back along d
    hit = np.zeros(len(near), bool)
    for t in np.arange(0.0, reach, GSD / 8):
        px, py = xs[near] - t * d[0], ys[near] - t * d[1]
        hit |= contains(fp, px, py) & (t <= (ROOF_Z - (GX * px + GY * py)) * cot)
    out = ground.copy()
    out.reshape(-1, 3)[near[hit]] = ROOF
    return out


def test_plane_fit_and_centroid_are_exact_on_clean_data():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-10, 10, size=(60, 2))
    h = 12.0 + 0.3 * xy[:, 0] - 0.7 * xy[:, 1]
    h[:6] += 9.0                                                    # lines that ran on over something behind
    (h0, gx, gy), share = plane_fit(xy, h, 0.25, prior=0.0)
    q = xy.mean(axis=0)
    assert (gx, gy) == pytest.approx((0.3, -0.7), abs=1e-9)
    assert h0 == pytest.approx(12.0 + 0.3 * q[0] - 0.7 * q[1], abs=1e-9)
    assert share == pytest.approx(54 / 60)
    square = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 2.0], [0.0, 2.0]])
    assert area_centroid(square) == pytest.approx((2.0, 1.0))
    tri = np.array([[0.0, 0.0], [3.0, 0.0], [0.0, 3.0]])
    assert area_centroid(tri) == pytest.approx((1.0, 1.0))


def _scene_lines(fp: Footprint):
    """{view: its silhouette lines (or why none)} of ``fp`` on the synthetic maps, and each view's cot φ."""
    rng = np.random.default_rng(4)
    grid = Grid.north_up(-SIZE * GSD / 2, SIZE * GSD / 2, GSD, SIZE, SIZE)
    ground = _ground(rng)
    alpha = np.full((SIZE, SIZE), 255, np.uint8)
    win = grid.window_covering(Extent(*fp.bounds), 6)
    s = MatchSettings(max_height=60.0)
    lines, cots = {}, {}
    for pid in VIEWS:
        p = Perspective.from_id(pid)
        d, cot = horizontal_direction(p), relief_factor(p)
        t = grid.transform
        d_px = np.array([d[1] / t.e, d[0] / t.a])
        obl = _oblique(ground, fp, grid, pid)
        off = np.array([win.row0, win.col0], np.float64)            # both maps share the grid
        lines[pid] = silhouette_lines(fp, grid, win, d, d_px, cot, 60.0 * cot, (obl, alpha), off, (ground, alpha),
                                      off, s)
        cots[pid] = cot
    return lines, cots


def test_tinted_roof_on_sloped_ground_measured_at_the_mean_ground():
    fp = _footprint()
    lines, cots = _scene_lines(fp)
    for pid in VIEWS:
        cot = cots[pid]
        assert not isinstance(lines[pid], str), lines[pid]
        # each line: the roof above the ground at its outline point, within a quarter pixel of move
        expect = ROOF_Z - (GX * lines[pid].xy[:, 0] + GY * lines[pid].xy[:, 1])
        assert np.median(np.abs(lines[pid].h - expect)) < 0.5 * GSD / cot          # binary edges: ±0.5 px
    cx, cy = area_centroid(fp.rings[0])
    truth = ROOF_Z - (GX * cx + GY * cy)                             # roof minus the mean ground under it
    got = roof_heights(fp, lines)
    for pid in VIEWS:
        h, share, why = got[pid]
        assert why == "" and share > 0.8
        assert h == pytest.approx(truth, abs=0.1)
    # one view alone sees a single far edge: the slope across it is unknown, the height less sure
    alone = roof_heights(fp, {VIEWS[0]: lines[VIEWS[0]]})[VIEWS[0]]
    assert alone[2] == "" and abs(alone[0] - truth) > abs(got[VIEWS[0]][0] - truth)


def test_outline_ground_is_the_corners_ground_interpolated_along_each_edge():
    """The renderer subtracts the DTM per vertex: along an edge the ground is linear between its
    corners' DTM, not the DTM itself (here a curved one)."""
    fp = Footprint("q", (np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 4.0], [0.0, 4.0]]),))
    dtm = lambda x, y: 0.05 * x ** 2 + 3.0 * y  # noqa: E731
    xy = np.array([[2.5, 0.0], [10.0, 1.0], [7.0, 4.0], [0.0, 3.0]])
    want = [0.75 * dtm(0, 0) + 0.25 * dtm(10, 0), 0.75 * dtm(10, 0) + 0.25 * dtm(10, 4),
            0.7 * dtm(10, 4) + 0.3 * dtm(0, 4), 0.75 * dtm(0, 4) + 0.25 * dtm(0, 0)]
    assert outline_ground(fp, xy, dtm) == pytest.approx(want, abs=1e-12)


def test_levelled_lines_give_the_height_from_one_view_alone():
    """With the DTM the maps were drawn over, each line's height becomes roof − mean ground: one
    view's single far edge then gives the height as exactly as two views' plane does."""
    fp = _footprint()
    lines, cots = _scene_lines(fp)
    dtm = lambda x, y: GX * np.asarray(x) + GY * np.asarray(y)  # noqa: E731
    cx, cy = area_centroid(fp.rings[0])
    truth = ROOF_Z - (GX * cx + GY * cy)
    for pid in VIEWS:
        raw, cot = lines[pid], cots[pid]
        flat = levelled(fp, raw, dtm, float(dtm(cx, cy)))          # the mean of a linear ground: at the centroid
        assert np.median(np.abs(flat.h - truth)) < 0.5 * GSD / cot
        h, share, why = roof_heights(fp, {pid: flat}, slope=False)[pid]
        assert why == "" and share > 0.8
        assert h == pytest.approx(truth, abs=0.1)
        unlevelled = roof_heights(fp, {pid: raw})[pid][0]         # the same lines without the DTM: off by the slope
        assert abs(unlevelled - truth) > 2 * abs(h - truth)
