"""A building's views settled into its row: views that disagree with the others rejected, the rest combined."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from pipeline25d.analysis.heights.results import HeightRow, MatchSettings, ViewMeasurement


def drop_inconsistent(views: dict[str, ViewMeasurement], outlier_m: float) -> None:
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
        far = [p for p, h in acc.items()
               if abs(h - float(np.median([o for q, o in acc.items() if q != p]))) > outlier_m]
    for p in far:
        views[p] = replace(views[p], height=math.nan, reason="inconsistent")


def combine(fid: str, views: dict[str, ViewMeasurement], s: MatchSettings) -> HeightRow:
    """A building's row from its views: the median of the accepted views' heights, how many agree with
    it within ``s.agree_m``, and a quality that is their median quality times the share that agree."""
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
