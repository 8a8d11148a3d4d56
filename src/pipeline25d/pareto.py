"""The Pareto front of points on two objectives, both minimized."""

from __future__ import annotations

import math
from itertools import groupby


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point dominates, ordered by the first objective.

    A point dominates another when it is no worse on both objectives and better on one.
    Exact duplicates therefore all stay on the front (neither dominates the other); of
    points tied on one objective only those lowest on the other stay. A point with a
    non-finite coordinate (NaN, inf: a failed measurement) is neither on the front nor
    dominates anything. Equal first objectives are ordered by index.
    """
    finite = sorted((x, y, i) for i, (x, y) in enumerate(points) if math.isfinite(x) and math.isfinite(y))
    front: list[int] = []
    best_y = math.inf          # the lowest second objective among points with a smaller first one
    for _, group in groupby(finite, key=lambda p: p[0]):
        group = list(group)
        low = group[0][1]      # sorted: the group's lowest second objective comes first
        if low < best_y:
            front += [i for _, y, i in group if y == low]
            best_y = low
    return front
