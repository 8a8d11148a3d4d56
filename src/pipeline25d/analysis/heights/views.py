"""Every footprint on every oblique view, then each building's views settled, checked and combined."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from pipeline25d.analysis.evaluate.rasters import _open
from pipeline25d.analysis.ground_under import Sampler, dtm_under
from pipeline25d.analysis.heights.combine import combine, drop_inconsistent
from pipeline25d.analysis.heights.matcher import MatchResult, _Matcher
from pipeline25d.analysis.heights.pitched import (
    KINDS,
    MAX_LOSS,
    fit_eave,
    lines_roof,
    ridge_height,
    rise_share,
    roof_frame,
    roof_ground,
    view_rise,
)
from pipeline25d.analysis.heights.results import NADIR_ID, HeightRow, MatchSettings, ViewMeasurement
from pipeline25d.analysis.heights.silhouette import (
    MIN_CONSISTENT,
    Lines,
    levelled,
    robust_level,
    roof_heights,
    silhouette_lines,
)
from pipeline25d.analysis.heights.template import _PAD, Template, _prepare_view, _View, build_template
from pipeline25d.core.errors import InputFileError
from pipeline25d.core.grid import Extent, Grid, Window
from pipeline25d.core.raster import read_rgba_block
from pipeline25d.formats.footprints import Footprint
from pipeline25d.geometry.camera import horizontal_direction
from pipeline25d.geometry.perspectives import Perspective

log = logging.getLogger(__name__)

#: a colour height this far above the silhouette's level: the ridge is fitted from that level too
PITCHED_GAP_M = 1.0


def measure_parallel(map_paths: dict[str, str | Path], footprints: list[Footprint],
                     settings: MatchSettings | None = None, workers: int = 1, block: int = 64,
                     ground: Callable[[], Sampler] | None = None) -> list[HeightRow]:
    """:func:`measure_heights` over blocks of ``block`` footprints (in west-to-east order, so a
    block's maps are read from nearby windows) on ``workers`` processes; the same rows, in input
    order. Every footprint is measured alone, so the cost is footprints × views ÷ workers.
    ``ground``: as for :func:`measure_heights` (a picklable factory, called in each process)."""
    if workers <= 1 or len(footprints) <= block:
        return measure_heights(map_paths, footprints, settings=settings, ground=ground)
    from concurrent.futures import ProcessPoolExecutor

    from pipeline25d.core.stopping import die_on_stop_signals

    order = sorted(range(len(footprints)), key=lambda i: footprints[i].bounds[0])
    blocks = [order[k:k + block] for k in range(0, len(order), block)]
    rows: list[HeightRow | None] = [None] * len(footprints)
    with ProcessPoolExecutor(max_workers=workers, initializer=die_on_stop_signals) as pool:
        futures = [pool.submit(measure_heights, map_paths, [footprints[i] for i in b], NADIR_ID, settings,
                               footprints, ground) for b in blocks]
        for b, f in zip(blocks, futures):
            for i, row in zip(b, f.result()):
                rows[i] = row
    return [r for r in rows if r is not None]


def measure_heights(map_paths: dict[str, str | Path], footprints: list[Footprint], nadir_id: str = NADIR_ID,
                    settings: MatchSettings | None = None,
                    context: list[Footprint] | None = None,
                    ground: Callable[[], Sampler] | None = None) -> list[HeightRow]:
    """Height of every footprint in every oblique map of ``map_paths`` ({perspective id: GeoTIFF}).

    The maps must share the nadir map's CRS (CRSError naming them otherwise); footprints are
    in that CRS. A view left ambiguous (rival peaks) is settled by the others when exactly one
    of its rivals lies within ``agree_m`` of the height they give (the accepted views' median,
    or else the one height that rivals of two or more views share); such a view is marked
    ``resolved``. ``context``: every footprint of the scene, for the silhouette's neighbours
    (default ``footprints``). ``ground``: makes the sampler of the ground the maps were drawn
    over (the scene's DTM); with it the silhouette's lines are levelled exactly
    (:func:`.silhouette.levelled`), without it a plane through them estimates the slope.
    Returns one row per footprint, in input order.
    """
    s = settings or MatchSettings()
    if nadir_id not in map_paths:
        raise InputFileError(nadir_id, f"no nadir map {nadir_id!r} among {sorted(map_paths)}")
    nad_path = map_paths[nadir_id]
    nad = _open(nad_path)
    grid = Grid.of_dataset(nad)
    if abs(grid.transform.a + grid.transform.e) > 1e-9 * grid.transform.a:
        raise InputFileError(nad_path, f"pixels must be square, geotransform {grid.geotransform}")
    views = [_prepare_view(pid, path, nad, nad_path) for pid, path in sorted(map_paths.items())
             if pid != nadir_id and Perspective.from_id(pid).elevation != 90]
    step_m = grid.res
    sample = ground() if ground is not None else None
    pad = s.ring_px + 4
    rows_out: list[HeightRow] = []
    context = footprints if context is None else context
    bounds = np.array([f.bounds for f in context], dtype=np.float64).reshape(-1, 4)
    for fp in footprints:
        win = grid.window_covering(Extent(*fp.bounds), pad)
        c0, r0, c1, r1 = win
        if win.col1 <= 0 or win.row1 <= 0 or win.col0 >= grid.width or win.row0 >= grid.height:
            tmpl: Template | str = "outside_nadir"
        else:
            nad_rgb, nad_alpha = read_rgba_block(nad, win.col0, win.row0, win.width, win.height)
            tmpl = build_template(fp, grid, win, nad_rgb, nad_alpha, s)
        results: dict[str, MatchResult] = {}
        matchers: dict[str, _Matcher] = {}
        pending: dict[str, tuple] = {}
        for v in views:
            if isinstance(tmpl, str):
                results[v.pid] = MatchResult(math.nan, 0.0, 1.0, tmpl)
                continue
            u_max = s.max_height * v.cot
            o_r0, o_c0, o_r1, o_c1 = oblique_window(v, win, u_max, step_m)
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
            if not results[v.pid].reason and results[v.pid].u < s.min_colour_m * v.cot:
                results[v.pid] = replace(results[v.pid], reason="low")
            pending[v.pid] = (v, u_max, (obl_rgb, obl_alpha), off, (sw_rgb, sw_alpha), sweep[2])
        cot = {v.pid: v.cot for v in views}
        resolved = _resolve(results, matchers, cot, s.agree_m + step_m / max(min(cot.values(), default=1.0), 1e-9))
        base = dtm_under(fp, sample, step_m) if sample is not None else math.nan

        def all_lines() -> dict[str, Lines | str]:
            """Every view's silhouette lines (levelled where the DTM is known)."""
            out = {p: silhouette_lines(fp, grid, win, horizontal_direction(Perspective.from_id(p)), v.d_px, v.cot,
                                       u_max, obl, off, nad_sw, nad_off, s, _neighbours(fp, context, bounds))
                   for p, (v, u_max, obl, off, nad_sw, nad_off) in pending.items()}
            if np.isfinite(base):
                out = {p: levelled(fp, v, sample, base) if isinstance(v, Lines) else v for p, v in out.items()}
            return out

        lines: dict[str, Lines | str] = {}
        if s.silhouette and any(results[p].reason for p in pending):
            # every view's lines (their far outlines together show the ground's slope), for the failed views
            lines = all_lines()
            _by_silhouette(fp, results, lines, cot, 2 * s.agree_m, slope=not np.isfinite(base))
        measurements = {}
        for pid, r in results.items():
            reason = r.reason
            if not reason and not (-step_m <= r.u <= s.max_height * cot[pid] + step_m):
                reason = "out_of_range"
            h = r.u / cot[pid] if not reason else math.nan
            measurements[pid] = ViewMeasurement(h, r.u, r.match * (1.0 - r.second), r.match, r.second, reason,
                                                pid in resolved, r.method)
        drop_inconsistent(measurements, s.outlier_m)
        row = combine(fp.id, measurements, s)
        if np.isfinite(row.height) and isinstance(tmpl, Template):
            around = {p: (v, obl[0], off) for p, (v, _, obl, off, _, _) in pending.items()}
            row = _roof(fp, row, measurements, cot, s,
                        lambda r: _with_ridge(r, fp, tmpl, grid, win, around, sample, step_m, s.tol),
                        (lambda: lines or lines.update(all_lines()) or lines) if np.isfinite(base) and s.silhouette
                        else None, sample)
        rows_out.append(row)
    return rows_out


def oblique_window(v: _View, win: Window, u_max: float, step_m: float) -> tuple[int, int, int, int]:
    """(row0, col0, row1, col1) of the oblique map ``v`` that a footprint's nadir window ``win``
    is searched in: that window moved by -3 .. u_max + 3 steps along the view, with a margin,
    clipped to the raster (empty where row1 <= row0 or col1 <= col0)."""
    c0, r0, c1, r1 = win
    corners = np.array([[r0, c0], [r0, c1], [r1, c0], [r1, c1]], dtype=np.float64)
    pts = np.concatenate([corners + v.offset + u * v.d_px for u in (-3 * step_m, u_max + 3 * step_m)])
    return (max(int(math.floor(pts[:, 0].min())) - _PAD, -_PAD), max(int(math.floor(pts[:, 1].min())) - _PAD, -_PAD),
            min(int(math.ceil(pts[:, 0].max())) + _PAD, v.src.RasterYSize + _PAD),
            min(int(math.ceil(pts[:, 1].max())) + _PAD, v.src.RasterXSize + _PAD))


def _roof(fp: Footprint, row: HeightRow, measurements: dict[str, ViewMeasurement], cot: dict[str, float],
          s: MatchSettings, ridge_fit: Callable[[HeightRow], HeightRow],
          get_lines: Callable[[], dict[str, "Lines | str"]] | None, sample: Sampler | None = None) -> HeightRow:
    """``row`` with its roof: the ridge and kind from the colours (``ridge_fit``), else from the
    silhouette's gable and hip ends; a pitched roof's eave then from the silhouette's lines with that
    ridge (its colours move by more than the eave's height, its gable ends' lines end above it),
    ``measurements`` updated in place. ``get_lines``: the levelled lines (None: no DTM, colours only);
    ``sample``: the DTM (the ground under the roof moves its points on the map, see
    :func:`.pitched.line_excess`)."""
    row = ridge_fit(row)
    if get_lines is None:
        return row
    from_lines = False
    if row.roof == "flat":
        low = _silhouette_level(get_lines())
        if low < row.height - PITCHED_GAP_M:
            # the colours moved the roof by more than its silhouette's level: a pitched roof's faces
            # rise above the eave; the ridge fitted from that level instead
            lower = ridge_fit(replace(row, height=low))
            if lower.roof in KINDS:
                row = replace(row, ridge=lower.ridge, roof=lower.roof, ridges=lower.ridges)
    if row.roof == "flat":
        # colours alike on both faces (the ridge along the light): the gable ends' silhouette
        row = _silhouette_ridge(fp, row, get_lines(), cot, sample)
        from_lines = row.roof in KINDS
    kept = _refit_eaves(fp, row, measurements, get_lines(), cot, s, sample) if row.roof in KINDS else None
    if kept is None or from_lines:
        return row if kept is None else kept
    again = ridge_fit(kept)
    return _ridge_checked(fp, again if again.roof in KINDS else kept, measurements, get_lines(), cot, s, sample)


def _refit_eaves(fp: Footprint, row: HeightRow, measurements: dict[str, ViewMeasurement],
                 lines: dict[str, "Lines | str"], cot: dict[str, float], s: MatchSettings,
                 sample: Sampler | None) -> HeightRow | None:
    """``row`` with its views' eaves fitted under its ridge (:func:`_eaves`, ``measurements`` in
    place) and combined again; None where no view's eave changed or none is left."""
    if not _eaves(fp, row, measurements, lines, cot, sample):
        return None
    drop_inconsistent(measurements, s.outlier_m)
    new = combine(fp.id, measurements, s)
    return replace(new, ridge=row.ridge, roof=row.roof, ridges=row.ridges) if np.isfinite(new.height) else None


def _ridge_checked(fp: Footprint, row: HeightRow, measurements: dict[str, ViewMeasurement],
                   lines: dict[str, "Lines | str"], cot: dict[str, float], s: MatchSettings,
                   sample: Sampler | None) -> HeightRow:
    """``row`` whose views' ridges differ by more than PITCHED_GAP_M (a view fitted its rise from a
    wrong eave) checked against the silhouette's gable ends (:func:`.pitched.silhouette_roof`): the
    view ridge within PITCHED_GAP_M of theirs, else their gabled roof, the eaves fitted again under
    it (``measurements`` in place); view ridges farther from it are dropped (NaN). Unchanged where
    the silhouette shows no gable."""
    ridges = [h for h in row.ridges.values() if np.isfinite(h)]
    if row.roof not in KINDS or len(ridges) < 2 or max(ridges) - min(ridges) <= PITCHED_GAP_M:
        return row
    kind, rise, eave, _ = lines_roof(fp, lines, cot, sample)
    if kind not in KINDS:
        return row
    target = eave + rise
    near = min(ridges, key=lambda h: abs(h - target))
    log.info("%s: view ridges %s disagree, the silhouette's gable says %.2f m", fp.id, np.round(ridges, 2), target)
    ridge = near if abs(near - target) <= PITCHED_GAP_M else target
    kept = {p: h if abs(h - ridge) <= PITCHED_GAP_M else math.nan for p, h in row.ridges.items()}
    if ridge == near:
        return replace(row, ridge=near, ridges=kept)
    row = replace(row, ridge=target, roof=kind, ridges=kept)
    new = _refit_eaves(fp, row, measurements, lines, cot, s, sample)
    return row if new is None else new


def _silhouette_level(lines: dict[str, "Lines | str"]) -> float:
    """The level of every view's levelled lines together (NaN without any)."""
    usable = [lv for lv in lines.values() if isinstance(lv, Lines)]
    if not usable:
        return math.nan
    return robust_level(np.concatenate([lv.h for lv in usable]), max(lv.inlier for lv in usable))[0]


def _silhouette_ridge(fp: Footprint, row: HeightRow, lines: dict[str, "Lines | str"], cot: dict[str, float],
                      sample: Sampler | None = None) -> HeightRow:
    """``row`` with the ridge and kind of :func:`.pitched.silhouette_roof` where it finds a rise."""
    kind, rise, eave, _ = lines_roof(fp, lines, cot, sample)
    if kind not in KINDS:
        return row
    return replace(row, ridge=eave + rise, roof=kind, ridges={p: math.nan for p in row.ridges})


def _eaves(fp: Footprint, row: HeightRow, measurements: dict[str, ViewMeasurement], lines: dict[str, "Lines | str"],
           cot: dict[str, float], sample: Sampler | None = None) -> bool:
    """Each view's eave of a pitched roof (``row.roof`` up to ``row.ridge``) from its silhouette lines
    (:func:`.pitched.fit_eave`), where enough of them agree (in place); whether any changed."""
    changed = False
    for p, m in measurements.items():
        lv = lines.get(p)
        if not isinstance(lv, Lines) or m.reason in ("too_small", "nadir_nodata", "outside_map"):
            continue
        d = horizontal_direction(Perspective.from_id(p))
        eave, share = fit_eave(fp, row.roof, row.ridge, lv.xy, lv.h, d, cot[p], lv.inlier, sample)
        if share < MIN_CONSISTENT:
            continue
        measurements[p] = replace(m, height=eave, shift_m=eave * cot[p], reason="", method="silhouette")
        changed = True
    return changed


def _with_ridge(row: HeightRow, fp: Footprint, tmpl: Template, grid: Grid, win, views: dict, sample: Sampler | None,
                step_m: float, tol: float) -> HeightRow:
    """``row`` with its ridge and roof kind (:mod:`.pitched`), from every view that has the map
    around the roof (``views``: {pid: (view, oblique RGB window, offset)}), the eave at its height."""
    x, y = grid.xy(win.col0 + tmpl.cols + 0.5, win.row0 + tmpl.rows + 0.5)
    xy = np.column_stack([x, y])
    excess = {k: np.zeros(len(xy)) for k in ("flat", *KINDS)}
    if sample is not None:
        base = dtm_under(fp, sample, step_m)
        frame = roof_frame(fp)
        # the ground the map subtracted under each pixel, were the roof of each kind (its vertices' DTM)
        g = {k: roof_ground(frame, k, sample, x, y, rise_share(frame, k, x, y) if k in KINDS else np.zeros(len(x)))
             for k in excess}
        if np.isfinite(base) and all(np.isfinite(v).all() for v in g.values()):
            excess = {k: v - base for k, v in g.items()}
    fits = {p: view_rise(fp, tmpl, xy, rgb, off, v.d_px, v.cot, row.height, excess, tol)
            for p, (v, rgb, off) in views.items()}
    ridge, kind = ridge_height(fits, row.height)
    per_view = {p: row.height + f.rise if f.loss <= MAX_LOSS else math.nan for p, f in fits.items()}
    return replace(row, ridge=ridge, roof=kind, ridges=per_view)


def _neighbours(fp: Footprint, footprints: list[Footprint], bounds: np.ndarray, margin: float = 4.0) -> list[Footprint]:
    """The other footprints whose bounding boxes come within ``margin`` m of ``fp``'s."""
    b = np.asarray(fp.bounds)
    near = ((bounds[:, 0] <= b[2] + margin) & (bounds[:, 2] >= b[0] - margin)
            & (bounds[:, 1] <= b[3] + margin) & (bounds[:, 3] >= b[1] - margin))
    return [footprints[i] for i in np.flatnonzero(near) if footprints[i] is not fp]


def _by_silhouette(fp: Footprint, results: dict[str, MatchResult], lines: dict[str, "Lines | str"],
                   cot: dict[str, float], outlier_m: float, slope: bool = True) -> None:
    """Where the colours give no height (or one below ``min_colour_m``: a roof matched on its own
    wall of the same tint), the silhouette's (:mod:`.silhouette`); in place. Such a view takes its
    silhouette's height, unless colour matches of other views (ambiguous ones settled first) exist
    and it lies more than ``outlier_m`` (the caller: 2 × agree_m) from their median
    ("silhouette_disagrees": a hidden roof's lines end where its occluder ends). A lone colour match
    that its own view's silhouette and another view's both put more than ``outlier_m`` elsewhere is
    rejected ("contradicted"); one that another view's silhouette alone disagrees with is rejected
    with it ("inconsistent"). A view neither measures keeps both reasons (colour+silhouette)."""
    usable = {p: v for p, v in lines.items() if not isinstance(v, str)}
    found = roof_heights(fp, usable, slope) if usable else {}
    sil = {p: found.get(p, (math.nan, 0.0, v if isinstance(v, str) else "")) for p, v in lines.items()}
    colour = {p: r.u / cot[p] for p, r in results.items() if not r.reason}
    if len(colour) == 1:
        # one colour match alone, and its own view's silhouette, backed by another view's, puts the
        # roof elsewhere: the colours matched a like roof further along the view
        (p, h_c), = colour.items()
        h_s, _, why = sil.get(p, (math.nan, 0.0, "none"))
        if (not why and abs(h_c - h_s) > outlier_m
                and any(not w and q != p and abs(h - h_s) <= outlier_m for q, (h, _, w) in sil.items())):
            results[p] = replace(results[p], reason="contradicted")
            colour = {}
    ref = float(np.median(list(colour.values()))) if colour else math.nan
    for p, (h, share, why) in sil.items():
        if not results[p].reason or results[p].reason in ("too_small", "nadir_nodata", "outside_map"):
            continue
        if not why and np.isfinite(ref) and abs(h - ref) > outlier_m:
            why = "silhouette_disagrees"
            if len(colour) == 1:          # two views, two heights: no telling which one is right
                (q, _), = colour.items()
                results[q] = replace(results[q], reason="inconsistent")
        if why:
            results[p] = replace(results[p], reason=f"{results[p].reason}+{why}")
        else:
            results[p] = MatchResult(h * cot[p], share, 0.0, "", method="silhouette")


def _resolve(results: dict[str, MatchResult], matchers: dict[str, "_Matcher"], cot: dict[str, float],
             tol_h: float) -> set[str]:
    """Settle ambiguous views by the height the others give (in place); returns the settled views."""
    amb = [p for p, r in results.items() if r.reason.startswith("ambiguous") and p in matchers]
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
