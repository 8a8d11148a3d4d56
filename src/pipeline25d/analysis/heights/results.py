"""The matcher's settings, a view's measurement, a building's row, and the heights CSV."""

from __future__ import annotations

import csv
import io
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline25d.core.errors import InputFileError
from pipeline25d.geometry.perspectives import ID_PATTERN

log = logging.getLogger(__name__)


NADIR_ID = "az000_el90"


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
    silhouette: bool = True       # where the roof's colours give no height, where the building ends does
    min_colour_m: float = 1.0     # a colour match lower than this is taken for the roof's own wall ("low")


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
    method: str = "colour"        # how: colour (the roof template) or silhouette (where the building ends)


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
    ridge: float = math.nan       # ridge height (pitched roofs; the height itself on flat ones), NaN unmeasured
    roof: str = ""                # the roof kind the ridge's fit chose: flat, gabled, hipped ('' unmeasured)
    ridges: dict[str, float] = field(default_factory=dict, repr=False)   # per view: eave + that view's rise


def write_csv(path: str | Path, rows: list[HeightRow], extra: dict[str, dict[str, str]] | None = None) -> None:
    """One line per building: id, height, n_views, n_agree, quality, the ``extra`` columns
    ({column: {id: text}}, e.g. a reference), then per view height, quality, reason ('' =
    accepted) and resolved (1 = settled by the other views) and method (colour: the roof's template,
    silhouette: where the building ends); unmeasured heights empty."""
    from pipeline25d.core.atomic import write_text

    extra = extra or {}
    views = sorted({k for r in rows for k in r.heights})
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["id", "height", "n_views", "n_agree", "quality", *extra]
               + [f"{p}_{v}" for v in views for p in ("height", "quality", "reason", "resolved", "method")])
    fmt = lambda x: "" if not np.isfinite(x) else f"{x:.3f}"  # noqa: E731
    for r in rows:
        w.writerow([r.id, fmt(r.height), r.n_views, r.n_agree, f"{r.quality:.3f}",
                    *(c.get(r.id, "") for c in extra.values())]
                   + [x for v in views for x in (fmt(r.heights.get(v, math.nan)), f"{r.qualities.get(v, 0.0):.3f}",
                                                 r.reasons.get(v, "missing"),
                                                 int(r.views[v].resolved) if v in r.views else 0,
                                                 r.views[v].method if v in r.views else "")])
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
