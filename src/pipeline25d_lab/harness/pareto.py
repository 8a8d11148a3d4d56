"""The Pareto front of points on two objectives, both minimized."""

from __future__ import annotations

import math


def pareto_front(points: list[tuple[float, float]], tolerance: tuple[float, float] = (0.0, 0.0)) -> list[int]:
    """Indices of the points no other point dominates, ordered by the first objective.

    A point dominates another when it is no worse on both objectives and better on one by
    more than that objective's ``tolerance`` (a measurement's noise: a run 0.5 s faster within
    a 2 s noise band is not better). Exact duplicates therefore all stay on the front (neither
    dominates the other). A point with a non-finite coordinate (NaN, inf: a failed
    measurement) is neither on the front nor dominates anything. Equal first objectives are
    ordered by index.
    """
    tx, ty = tolerance
    finite = [(x, y, i) for i, (x, y) in enumerate(points) if math.isfinite(x) and math.isfinite(y)]

    def dominates(a: tuple, b: tuple) -> bool:
        return a[0] <= b[0] and a[1] <= b[1] and (a[0] < b[0] - tx or a[1] < b[1] - ty)

    return [p[2] for p in sorted(finite) if not any(dominates(q, p) for q in finite)]
