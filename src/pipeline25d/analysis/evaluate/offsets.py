"""Ground offsets of one oblique map against the nadir map, over windows of visible ground; the result record."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline25d.analysis.evaluate.correlation import _INTERP_MARGIN, measure_window
from pipeline25d.analysis.evaluate.rasters import _open, _pair_grids, _read_block, _read_window, _same_crs
from pipeline25d.analysis.evaluate.visibility import GroundMaskFn, GroundModel, perspective_of
from pipeline25d.core.errors import CRSError
from pipeline25d.core.grid import Grid
from pipeline25d.geometry.perspectives import Perspective

log = logging.getLogger(__name__)




MIN_OK_WINDOWS = 10           # fewer ok windows than this: no summary figures ("n/a")


FAIL_REASONS = ("too_few_pixels", "ill_conditioned", "no_convergence", "shift_too_large", "low_correlation",
                "ambiguous_peak")   # in the order they are checked


@dataclass
class OffsetResult:
    """Ground offsets of one oblique map against the nadir map.

    Per-window arrays cover every correlated window (``n_windows`` of them, ok or failed):
    ``x``, ``y`` window centre in map coordinates (metres, nadir position), ``dx_px``/``dy_px``
    offset in map pixels (x east, y north; see module docstring), ``quality`` normalised
    cross-correlation of the aligned usable pixels (−1..1), ``peak_ratio`` second-highest /
    highest local maximum of the masked NCC surface, ``ok`` whether the window passed,
    ``reason`` why not ('' if ok), ``ground_fraction`` share of the window's pixels that are
    usable (opaque in both maps and visible ground), ``n_px`` pixels in the fit,
    ``condition`` condition number of the fit's 2×2 shift normal matrix (gain and offset
    eliminated), ``sigma_px`` formal standard error of the shift (larger semi-axis; residuals are
    spatially correlated, so it understates the real error). Summary figures use ok windows
    only and are None with fewer than MIN_OK_WINDOWS.
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
    n_transparent: int            # excluded: < min_ground_fraction of pixels opaque in both maps
    n_flat: int                   # excluded: grey std of the usable pixels <= min_texture in either map
    n_not_ground: int             # excluded: < min_ground_fraction of pixels opaque and visible ground
    x: np.ndarray = field(repr=False)
    y: np.ndarray = field(repr=False)
    dx_px: np.ndarray = field(repr=False)
    dy_px: np.ndarray = field(repr=False)
    quality: np.ndarray = field(repr=False)
    peak_ratio: np.ndarray = field(repr=False)
    ok: np.ndarray = field(repr=False)
    reason: list[str] = field(repr=False)
    ground_fraction: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    n_px: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    condition: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    sigma_px: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    perspective: str = ""         # view whose visible-ground mask was used ('' without a ground model)
    min_ground_fraction: float = 0.3

    @property
    def n_windows(self) -> int:
        return int(len(self.ok))

    @property
    def n_ok(self) -> int:
        return int(np.count_nonzero(self.ok))

    @property
    def n_failed(self) -> int:
        return self.n_windows - self.n_ok

    def failed_by_reason(self) -> dict[str, int]:
        return {r: self.reason.count(r) for r in sorted(set(self.reason)) if r}

    def summary(self) -> dict[str, Any]:
        """Counts plus rms/median/p95 of the offset length and the mean vector (bias), px and m."""
        out: dict[str, Any] = {"n_windows": self.n_windows, "n_ok": self.n_ok, "n_failed": self.n_failed,
                               "failed_by_reason": self.failed_by_reason()}
        keys = ("rms", "median", "p95", "bias_x", "bias_y")
        if self.n_ok < MIN_OK_WINDOWS:
            out.update({f"{k}_{u}": None for k in keys for u in ("px", "m")})
            out["mean_ground_fraction"] = None
            return out
        dx, dy = self.dx_px[self.ok], self.dy_px[self.ok]
        length = np.hypot(dx, dy)
        px = {"rms": float(np.sqrt(np.mean(length ** 2))), "median": float(np.median(length)),
              "p95": float(np.percentile(length, 95)), "bias_x": float(dx.mean()), "bias_y": float(dy.mean())}
        for k in keys:
            out[f"{k}_px"] = round(px[k], 4)
            out[f"{k}_m"] = round(px[k] * self.gsd_m, 4)
        out["mean_ground_fraction"] = (round(float(self.ground_fraction[self.ok].mean()), 3)
                                       if len(self.ground_fraction) == len(self.ok) else None)
        return out

    def summary_line(self) -> str:
        """One line, e.g. ``az045_el45: 812 windows, 790 ok, rms 0.31 px (0.08 m), p95 0.60 px,
        bias (+0.02, -0.05) px``; "n/a (N windows)" instead of figures from < MIN_OK_WINDOWS ok
        windows; then the failures by reason and the excluded grid windows."""
        s = self.summary()
        line = f"{self.name}: {self.n_windows} windows, {self.n_ok} ok, "
        if s["rms_px"] is None:
            line += f"n/a ({self.n_ok} windows)"
        else:
            line += (f"rms {s['rms_px']:.2f} px ({s['rms_m']:.2f} m), p95 {s['p95_px']:.2f} px, "
                     f"bias ({s['bias_x_px']:+.2f}, {s['bias_y_px']:+.2f}) px")
        if s["failed_by_reason"]:
            line += "; failed " + ", ".join(f"{n} {r}" for r, n in s["failed_by_reason"].items())
        excluded = [f"{n} {what}" for n, what in ((self.n_transparent, "transparent"), (self.n_flat, "flat"),
                                                  (self.n_not_ground, "not ground")) if n]
        if excluded:
            line += "; excluded " + ", ".join(excluded)
        if self.resampled:
            line += "; oblique resampled onto the nadir grid"
        return line

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: settings, counts, summary and the per-window columns."""
        def col(values, nd):
            return [None if not np.isfinite(v) else round(float(v), nd) for v in values]

        return {
            "name": self.name, "oblique": self.oblique, "nadir": self.nadir, "gsd_m": self.gsd_m,
            "window_px": self.window_px, "step_px": self.step_px, "resampled": self.resampled, "note": self.note,
            "perspective": self.perspective, "min_ground_fraction": self.min_ground_fraction,
            "n_grid": self.n_grid, "n_examined": self.n_examined, "n_transparent": self.n_transparent,
            "n_flat": self.n_flat, "n_not_ground": self.n_not_ground,
            "summary": self.summary(),
            "windows": {
                "x": col(self.x, 3), "y": col(self.y, 3), "dx_px": col(self.dx_px, 3), "dy_px": col(self.dy_px, 3),
                "quality": col(self.quality, 4), "peak_ratio": col(self.peak_ratio, 4),
                "ok": [bool(v) for v in self.ok], "reason": list(self.reason),
                "ground_fraction": col(self.ground_fraction, 3), "n_px": [int(v) for v in self.n_px],
                "condition": col(self.condition, 2), "sigma_px": col(self.sigma_px, 4),
            },
        }


def ground_offsets(oblique_tif: str | Path, nadir_tif: str | Path,
                   ground_mask_fn: GroundModel | GroundMaskFn | None = None, window_px: int = 32,
                   step_px: int | None = None, min_texture: float = 4.0, max_windows: int = 2000, seed: int = 0,
                   min_ncc: float = 0.5, max_peak_ratio: float = 0.95, max_shift_px: float | None = None,
                   min_ground_fraction: float = 0.3, max_condition: float = 25.0,
                   perspective: Perspective | str | None = None) -> OffsetResult:
    """Measure where the oblique map shows the ground relative to the nadir map, window by window.

    Windows of ``window_px``² nadir-grid pixels are cut every ``step_px`` (default: window_px)
    over the overlap of the two maps. A pixel is usable when it is fully opaque (alpha 255) in
    both maps and the ground mask says True for its centre. The mask: a :class:`GroundModel`
    gives ground the oblique view sees (its perspective from ``perspective`` or the oblique file
    name stem, ConfigError if neither names one) and that is ground in the nadir view; a plain
    GroundMaskFn is used as it is, for both maps (``perspective`` is then not used); None: every
    pixel. A window is used when at
    least ``min_ground_fraction`` of its pixels are usable (else excluded as 'transparent' if
    too few are opaque in both maps, 'not ground' otherwise) and the grey std of its usable
    pixels exceeds ``min_texture`` (0–255 grey levels) in both maps (else 'flat'). Grid windows
    are visited in a seeded random order until ``max_windows`` are used. Each used window is
    registered by :func:`measure_window` (masked NCC, then Gauss–Newton with gain and offset)
    and fails (counted, never dropped) as 'too_few_pixels', 'ill_conditioned' (condition >
    ``max_condition``), 'no_convergence', 'shift_too_large' (> ``max_shift_px``, default
    window_px/4), 'low_correlation' (aligned NCC < ``min_ncc``; an integer NCC peak below
    ``min_ncc``/2 fails so before anything else) or 'ambiguous_peak' (second local maximum of
    the NCC surface > ``max_peak_ratio`` × the first), checked in that order. Defaults (window
    32 px, min_ground_fraction 0.3, max_peak_ratio 0.95, max_condition 25) were chosen on the
    Delft LiDAR mesh, where ~13 % of the cells are ground after dilation.
    Maps must share the CRS. An oblique origin off the nadir grid by a fraction of a pixel is
    handled exactly (nearest-pixel pairing plus the known fraction); a different gsd makes the
    oblique map be resampled bilinearly onto the nadir grid (noted).
    """
    step_px = int(step_px or window_px)
    max_shift_px = window_px / 4 if max_shift_px is None else float(max_shift_px)
    search = int(math.ceil(max_shift_px)) + 1
    margin = search + _INTERP_MARGIN
    nad, obl = _open(nadir_tif), _open(oblique_tif)
    if not _same_crs(nad.GetProjection(), obl.GetProjection()):
        raise CRSError(f"{oblique_tif} and {nadir_tif} are in different CRSs")
    view = ""
    mask_fn: GroundMaskFn | None = ground_mask_fn
    if isinstance(ground_mask_fn, GroundModel):
        p = perspective_of(oblique_tif, perspective)
        view = p.id
        mask_fn = ground_mask_fn.mask(None) & ground_mask_fn.mask(p)
    ng = Grid.of_dataset(nad)
    gsd = ng.res
    pair = _pair_grids(obl, nad, oblique_tif)
    src, (oc, orow), (nc, nr), (w, h) = pair.src, pair.obl_off, pair.nad_off, pair.size

    cols = np.arange(0, w - window_px + 1, step_px) if w >= window_px else np.zeros(0, int)
    rows = np.arange(0, h - window_px + 1, step_px) if h >= window_px else np.zeros(0, int)
    grid = [(int(r), int(c)) for r in rows for c in cols]
    order = np.random.default_rng(seed).permutation(len(grid))
    big = window_px + 2 * margin
    centre = np.arange(big) + 0.5 - margin               # block pixel centres, relative to the window
    inner = slice(margin, margin + window_px)
    need = min_ground_fraction * window_px * window_px

    counts = {"transparent": 0, "flat": 0, "not_ground": 0}
    keys = ("x", "y", "dx", "dy", "q", "pr", "ok", "reason", "gf", "npx", "cond", "sig")
    out: dict[str, list] = {k: [] for k in keys}
    n_examined = 0
    for i in order:
        if len(out["ok"]) >= max_windows:
            break
        n_examined += 1
        r, c = grid[i]
        gn_grey, an = _read_window(nad, nc + c, nr + r, window_px)
        opaque_n = an == 255
        if np.count_nonzero(opaque_n) < need:
            counts["transparent"] += 1
            continue
        go_grey, ao = _read_block(src, oc + c - margin, orow + r - margin, big)
        opaque_o = ao == 255
        if np.count_nonzero(opaque_n & opaque_o[inner, inner]) < need:
            counts["transparent"] += 1
            continue
        xs, ys = ng.xy(nc + c + centre, nr + r + centre)      # cell centres of the window's columns, rows
        if mask_fn is not None:
            xx, yy = np.meshgrid(xs, ys)
            ground = np.asarray(mask_fn(xx, yy), bool)
        else:
            ground = np.ones((big, big), bool)
        ok_o = opaque_o & ground
        ok_n = opaque_n & ground[inner, inner]
        both = ok_n & ok_o[inner, inner]
        n_both = int(np.count_nonzero(both))
        if n_both < need:
            counts["not_ground"] += 1
            continue
        if gn_grey[both].std() <= min_texture or go_grey[inner, inner][both].std() <= min_texture:
            counts["flat"] += 1
            continue
        fit = measure_window(gn_grey, ok_n, go_grey, ok_o, search, max_condition, min_ncc)
        reason = fit.reason
        if not reason and math.hypot(fit.d_col, fit.d_row) > max_shift_px:
            reason = "shift_too_large"
        if not reason and not fit.ncc >= min_ncc:
            reason = "low_correlation"
        if not reason and fit.peak_ratio > max_peak_ratio:
            reason = "ambiguous_peak"
        out["x"].append(float(xs[inner].mean()))
        out["y"].append(float(ys[inner].mean()))
        out["dx"].append(fit.d_col + pair.frac[0])
        out["dy"].append(-(fit.d_row + pair.frac[1]))
        out["q"].append(fit.ncc)
        out["pr"].append(fit.peak_ratio)
        out["ok"].append(not reason)
        out["reason"].append(reason)
        out["gf"].append(n_both / window_px ** 2)
        out["npx"].append(fit.n_px)
        out["cond"].append(fit.condition)
        out["sig"].append(fit.sigma_px)

    f = lambda k: np.asarray(out[k], dtype=float)  # noqa: E731
    return OffsetResult(
        name=Path(oblique_tif).stem, oblique=str(oblique_tif), nadir=str(nadir_tif), gsd_m=float(gsd),
        window_px=window_px, step_px=step_px, resampled=pair.resampled, note=pair.note,
        n_grid=len(grid), n_examined=n_examined, n_transparent=counts["transparent"], n_flat=counts["flat"],
        n_not_ground=counts["not_ground"], x=f("x"), y=f("y"), dx_px=f("dx"), dy_px=f("dy"),
        quality=f("q"), peak_ratio=f("pr"), ok=np.asarray(out["ok"], dtype=bool), reason=out["reason"],
        ground_fraction=f("gf"), n_px=np.asarray(out["npx"], dtype=int), condition=f("cond"), sigma_px=f("sig"),
        perspective=view, min_ground_fraction=min_ground_fraction)
