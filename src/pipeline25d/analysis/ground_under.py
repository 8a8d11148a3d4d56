"""The ground and the roof under a building's footprint, sampled on a grid inside its outline:
the references heights are measured against (see :mod:`pipeline25d.analysis.height_sources`)."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from pipeline25d.formats.footprints import Footprint, inside_points
from pipeline25d.stages.records import Scene

Sampler = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _inside_values(fp: Footprint, sample: Sampler, step: float, margin: float = 0.0) -> np.ndarray:
    """The finite values of ``sample(x, y)`` on :func:`inside_points`."""
    pts = inside_points(fp, step, margin)
    z = sample(pts[:, 0], pts[:, 1])
    return z[np.isfinite(z)]


def dtm_under(fp: Footprint, sample: Sampler, step: float) -> float:
    """Mean of the ground ``sample(x, y)`` over a ``step`` grid inside the footprint (NaN where none)."""
    z = _inside_values(fp, sample, step)
    return float(z.mean()) if len(z) else math.nan


def ground_range_under(fp: Footprint, sample: Sampler, step: float) -> tuple[float, float]:
    """(lowest, highest) ground ``sample(x, y)`` on a ``step`` grid inside the footprint (NaN where none)."""
    z = _inside_values(fp, sample, step)
    return (float(z.min()), float(z.max())) if len(z) else (math.nan, math.nan)


def dsm_roof(fp: Footprint, sample: Sampler, cell: float) -> float:
    """Median of the model's DSM over its cells inside the footprint, one cell in from the outline."""
    z = _inside_values(fp, sample, cell, margin=cell)
    return float(np.median(z)) if len(z) else math.nan


def ground_sampler(scene: Scene, scene_crs: str) -> Sampler:
    """The ground the maps were rendered over: the scene's DTM, or the plane z0 (terrain: flat)."""
    from pipeline25d.core.raster import DTM

    if not scene.dtm:
        z0 = float(scene.z0)
        return lambda x, y: np.full(len(x), z0)
    return DTM(scene.dtm, scene_crs, continuous=True).sample
